"""Tolerances in one place, each with its reason (SI units: m, rad, s)."""

#: Relative tolerance on |R_ii| / |R_00| below which a regressor column counts as
#: linearly dependent in the QR of the base-parameter analysis. The columns mix m and
#: rad, but for a 0.8 m arm the smallest genuine singular values sit around 1e-3 of the
#: largest, while numerically dependent ones fall to ~1e-14.
BASE_PARAM_RANK_RTOL = 1e-8

#: Coefficients of a base-parameter combination smaller than this are printed as zero
#: (they are round-off of the QR, not geometry).
BASE_PARAM_COEFF_ATOL = 1e-9

#: Gauss-Newton stops when the step in the base parameters is this small (m or rad).
IDENT_STEP_TOL = 1e-12

#: ... or when the relative decrease of the weighted cost is below this.
IDENT_COST_RTOL = 1e-12

#: Base parameters whose correlation coefficient exceeds this are reported as a pair.
STRONG_CORRELATION = 0.95

#: Below this angle (rad) rotation-vector formulas switch to their Taylor series.
SMALL_ANGLE = 1e-6

#: A CSV angle column whose magnitude exceeds this is taken to be in degrees, not rad
#: (no joint of a 6R arm turns more than 2*pi in one direction).
RADIANS_MAX_ABS = 2.0 * 3.141592653589793 + 1e-9

#: A position column whose magnitude exceeds this is taken to be in mm, not m
#: (no point of a cell is 20 m from F_I).
METRES_MAX_ABS = 20.0

#: Joint-limit slack (rad) when validating measured joint values (encoder rounding).
JOINT_LIMIT_SLACK = 1e-6

#: Joint-limit slack (rad) of the simulated controller: a command at a limit, computed in
#: float64 from the limits themselves (grid cells, via postures), lies within round-off of it.
JOINT_COMMAND_SLACK = 1e-9

#: Slack (rad) on |rotation vector| <= pi in a CSV: a rotation of exactly pi written with 17
#: significant digits may read back a few ulps above pi.
ROTVEC_NORM_SLACK = 1e-6

#: Smallest distance (m) between the base-frame set-up points, and of the y point from the
#: x axis, for the frame they define to be meaningful (the tracker's resolution is ~1 µm).
SETUP_POINT_MIN_SEPARATION_M = 1e-3

#: Held-out mean position error (m) up to which a model counts as at a noise floor of exactly 0
#: (noise-free measurements, e.g. a simulated tracker without noise): the round-off of a
#: float64 fit of a metre-sized arm, far below any tracker's noise (µm).
ZERO_NOISE_MODEL_ATOL_M = 1e-9
