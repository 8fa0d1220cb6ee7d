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

#: Joints read in degrees that all lie within RADIANS_MAX_ABS over this many rows are named as
#: radians (a program in degrees turns some joint beyond 6.3° in five poses; fewer rows may be a
#: small motion)
RADIANS_AS_DEGREES_MIN_ROWS = 5

#: ... when some joint of the file reads beyond this (3 turns' worth of rad, 19 in degrees: a
#: campaign in degrees turns some joint farther). Readings a little past 2*pi in a file that
#: reads no joint beyond it are radians past a limited joint's limit (a joint offset of another
#: convention, another robot), said by the limit check with its hint, not "looks like degrees"
DEGREES_EVIDENCE_ABS = 6.0 * 3.141592653589793

#: A position column whose magnitude exceeds this is taken to be in mm, not m
#: (no point of a cell is 20 m from F_I).
METRES_MAX_ABS = 20.0

#: Joint-limit slack (rad) when validating measured joint values (encoder rounding).
JOINT_LIMIT_SLACK = 1e-6

#: A joint reading further past its limit than this (rad for revolute joints, m for prismatic
#: ones) is no encoder reading slightly past a limit (TIAGo's torso reads 0.18 mm past; a few
#: hundredths of a degree is usual) but another robot's data: a forgotten --robot, not --limit-slack.
FAR_PAST_LIMIT_RAD = 0.0873  # 5 deg
FAR_PAST_LIMIT_M = 0.005

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

# -- plausibility (campaign/measure/plausibility.py): what a real robot and tracker can give --

#: Poses the plausibility checks look at (spread evenly over a larger campaign): the checks
#: compare whole-campaign statistics, which 2000 poses pin down to a few per cent.
PLAUSIBILITY_MAX_POSES = 2000

#: Measured positions spanning more than this factor times the nominal workspace (or less than
#: its inverse) are another unit or another robot: a campaign's poses cover the workspace the
#: nominal model predicts to within a few per cent (geometric errors are mm on a metre arm).
WORKSPACE_SCALE_MAX = 2.0

#: The nominal model's registered rms error above which the data and the model disagree beyond
#: geometric error: industrial arms are built to a few mm (the paper's COMAU: 2.4 mm mean before
#: calibration; large arms up to ~10 mm); 20 mm or 3 % of the stretched chain, whichever is larger.
NOMINAL_RESIDUAL_MAX_M = 0.020
NOMINAL_RESIDUAL_MAX_FRACTION_OF_SIZE = 0.03

#: A candidate joint convention is named when it cuts the registered rms by this factor (and
#: brings it under the nominal limit): a wrong convention errs by tens of cm, a right one by mm.
CONVENTION_GAIN_MIN = 10.0

#: Median mismatch of the distances between raw reflectors and their nominal positions above
#: which the layout is wrong: a tracker measures a reflector to ~10 µm and a nest is machined to
#: ~0.1 mm; 1 mm is a wrong order or a wrong tool.
REFLECTOR_DISTANCE_TOL_M = 1e-3

#: Mean angle between measured and nominal orientations (beyond one constant rotation) above
#: which the orientation columns are read wrongly: geometric errors turn a tool by mrad
#: (the paper: 3.6 mrad mean before calibration), a wrong Euler reading by tenths of a radian.
ORIENTATION_SPREAD_MAX_RAD = 0.05

#: An identified translation correction larger than this fraction of the stretched chain
#: (sum of the nominal link translations) reshapes the robot rather than correcting it: real
#: corrections are mm on a metre arm (0.1-1 %).
CORRECTION_MAX_FRACTION_OF_SIZE = 0.05

#: An identified rotation correction above this (rad, 5.7 deg) is not a manufacturing error:
#: zero offsets and axis tilts of real arms are a fraction of a degree.
CORRECTION_MAX_RAD = 0.1

#: The fit's own noise σ this many times below the measured (repeats) or stated tracker noise
#: means the model fits what the measurements cannot carry (the noise cannot be fitted away).
FITTED_NOISE_BELOW_FLOOR_FACTOR = 5.0

#: Without a known floor: a fitted position noise below this (m) is below any laser tracker's
#: (their single-point noise is 5-20 µm; the best interferometric modes ~0.5 µm + 0.4 µm/m).
TRACKER_NOISE_MIN_M = 0.3e-6

#: A training pose is a wild reading when its studentized residual exceeds the χ² quantile at this
#: family-wise level over the pose count (campaign.identify.outliers): a clean campaign of any size
#: then loses a pose in about 1 of 100 calibrations, and a 300 mm fault among 120 poses is ~10⁴ times the bound.
OUTLIER_ALPHA = 0.01
#: ... and beyond this factor on that bound: an effect the model lacks makes the residuals heavier-tailed
#: than Gaussian noise (up to 1.37x the bound over 160 simulated campaigns of 150 poses with a catalogued
#: effect missing, none of them a fault); a reading fault worth a word is tens of times beyond.
OUTLIER_FACTOR = 2.0
#: More flagged training poses than this share (or one, in a small campaign) are no isolated
#: reading faults but a systematic error or a moved set-up: kept in the fit and said.
OUTLIER_MAX_SHARE = 0.05

#: A calibrated model's held-out mean position error above this (5 mm, or 0.5 % of the stretched
#: chain) is no calibration: even uncalibrated arms are within a few mm, and a fit makes it better.
MODEL_RESIDUAL_MAX_M = 0.005
MODEL_RESIDUAL_MAX_FRACTION_OF_SIZE = 0.005

#: Quaternion columns whose norm differs from 1 by more than this are not unit quaternions (a
#: file's 6 printed digits keep the norm within 1e-5 of 1).
QUATERNION_NORM_TOL = 1e-3

#: Two measurements of one pose at most this far apart in time (s) are *back to back*: their
#: difference is the tracker's noise, and they give the noise floor (campaign.measure.floor);
#: repeats further apart measure the drift as well and are reported as drift
#: (campaign.measure.drift). A warm-up grows a metre-sized arm by up to ~1.5e-4 of its reach in
#: its first hour (~150 µm/h at 1 m); over 120 s that is 5 µm, which adds under 10 % to a
#: floor of a 10 µm tracker (σ of the tool origin ~6 µm per coordinate, successive differences
#: 2σ² + (5 µm)²/3 per coordinate). A back-to-back repeat of the plan (one tour pose in between)
#: takes 40-60 s in the default cell (2 s settle, 3 reflectors at 5 s, the motions).
REPEAT_CLOSE_S = 120.0

#: Without measurement times (an imported CSV without ``time_s``), repeats at most this many
#: rows apart count as back to back: 120 s at the default cell's ~25 s per pose.
REPEAT_CLOSE_ROWS = 5

#: the registration of an undeclared measured point (one reflector, robot.yaml names none) with the
#: tracker's pose alternates Kabsch and a linear least-squares step for the point: it stops when the
#: point moves less than this (far below a tracker's micrometres) ...
POINT_REGISTRATION_STEP_TOL_M = 1e-9
#: ... or after this many steps (a real campaign converges in under a hundred: FIGAROH's TIAGo, 82)
POINT_REGISTRATION_MAX_STEPS = 1000
#: the point's directions the tool's orientations determine worse than this (relative singular value
#: of the point's 3n x 3 design) stay at the tool frame's origin (min-norm least squares)
POINT_REGISTRATION_RCOND = 1e-6
#: ... and the point moves there only when it lies this many tool tolerances (robot.yaml's
#: ``tolerances: tool_m``) from the tool frame's origin: nearer, the data are read as measured at
#: the origin with the tool's own small error (a point moved by the other parameters' errors, a
#: fraction of a millimetre off the last joint's axis, would make the rotation about that axis
#: barely identifiable); FIGAROH's TIAGo marker is 110 mm away, 73 tolerances of 1.5 mm
POINT_REGISTRATION_MIN_TOLERANCES = 10.0

# -- a tracker's log matched to a program's stops (campaign.program.stream) ------------------------
#: length of a block of samples whose stillness is decided at once (s): short against a stop's
#: dwell (seconds), long enough for a robust spread (5 to 50 samples at 10 to 1,000 Hz)
STREAM_BLOCK_S = 0.2
#: a log's matched windows, fitted rigidly to the stops' nominal points, leave a median residual of
#: the nominal model's error (a fraction of a mm; a few mm on a badly built arm); another run's log, whose
#: successive distances can agree by chance, leaves hundreds: refused above this
STREAM_PLACEMENT_MAX_M = 0.01
#: a log said to be in the robot's base frame whose rigid fit to the stops moves them more than this
#: (a tracker's frame registered to the base is within a few mm) is in the tracker's frame
STREAM_ROBOT_FRAME_MAX_M = 0.05
#: blocks are laid from the start of each run of one reflector; a time gap longer than this many
#: sample intervals starts a new run (a lost sample or two does not)
STREAM_RUN_GAP_SAMPLES = 5.0
#: the still blocks' spread is the log's noise: this quantile of all blocks' spreads is taken as
#: a still block's (a calibration campaign dwells far more than a tenth of its time)
STREAM_NOISE_QUANTILE = 0.1
#: a block is still when its robust spread is below this many times the noise σ (a still block's
#: spread scatters by ~30 % about its mean; a tool creeping more than a few σ per block is moving)
STREAM_STILL_FACTOR = 5.0
#: the noise σ is never taken below this (m): a noise-free log rounded to 1 µm still has a level
STREAM_MIN_NOISE_M = 1e-6
#: a still block continues a window when its median is within this many still thresholds of the
#: window's first block of that reflector (the block median's scatter is far below one)
STREAM_SAME_PLACE_FACTOR = 3.0
#: a window survives this many moving blocks (a reflector change, a burst of spikes) ...
STREAM_SWITCH_BLOCKS = 2
#: ... and a gap this long (s) when the next block is another reflector (a tracker moves its beam
#: between reflectors in about a second)
STREAM_SWITCH_S = 2.0
#: a window survives a burst of spikes (or any disturbance) this long (s) when its reflector is then
#: back at its place: a robot cannot leave and come back to within the noise in that time
STREAM_BURST_S = 2.0
#: a time step longer than this many blocks' time inside a block makes the block a gap, not still
STREAM_GAP_BLOCKS = 3.0
#: a log is one record per stable point when its records are further apart in time than this (s):
#: a continuous one samples at 10 Hz or more
STREAM_POINT_MIN_DT_S = 0.25
#: records of one reflector within this (m) in a log of stable points are the same point
STREAM_POINT_STEP_M = 0.5e-3
#: samples kept of one open window (a long pause is thinned by two: its median is the same)
STREAM_WINDOW_MAX_SAMPLES = 200_000
#: the distance between two stops' tool points predicted by the nominal model and the distance
#: between their windows differ by the model's error: a few mm plus a share of the distance
#: (the geometric errors of an uncalibrated arm, Table 4's magnitudes)
STREAM_DISTANCE_TOL_M = 3e-3
STREAM_DISTANCE_TOL_REL = 0.01
#: stops skipped between two matched windows are bounded by the dwell they need: their dwells
#: sum to at most this factor of the time between the windows plus STREAM_DWELL_SLACK_S
STREAM_DWELL_FACTOR = 1.5
STREAM_DWELL_SLACK_S = 2.0
#: a reflector belongs to a window of the others when its distances to them are the tool's nominal
#: ones within this (m): a tool's reflectors sit within a millimetre or two of their drawing
STREAM_REFLECTOR_TOL_M = 3e-3
#: a matched window whose reflectors' rigid fit to the tool's layout leaves more than this rms (m)
#: is not stored as a pose (a reflector's window from elsewhere); a good fit leaves tens of µm
STREAM_FIT_RMS_MAX_M = 1e-3
#: a log of one reflector: a window longer than this many times the median of the recent windows
#: (STREAM_SPLIT_RECENT_WINDOWS, once STREAM_SPLIT_AFTER_WINDOWS are known) is that many stops at
#: one place (the program's dwells are equal; a window is a dwell less its edges)
STREAM_SPLIT_FACTOR = 1.6
STREAM_SPLIT_RECENT_WINDOWS = 200
STREAM_SPLIT_AFTER_WINDOWS = 5

#: The smallest error (mm) a log-scaled report figure shows: 1 pm, far below any tracker's
#: noise; smaller errors (exact data: a nominal model's own predictions, a perfect adapter)
#: are drawn at this value instead of at log10(0) = -inf.
REPORT_LOG_FLOOR_MM = 1e-9

#: A run stops when one pose's readings put two reflectors this many times farther apart (or
#: closer) than robot.yaml's reflector positions: a nest is machined to ~0.1 mm on distances of
#: 0.1 m (0.1 %) and a tracker reads to ~10 µm; 1.5× is a unit (mm: 1000×, inches: 39×) or
#: another tool, never a measurement.
READING_SPREAD_RATIO_MAX = 1.5

#: A reading farther than this from the tracker (m) is not a distance: the longest-range laser
#: trackers measure to 80 m (160 m across); a reading in mm of a reflector 0.2 m away is 200.
TRACKER_RANGE_MAX_M = 160.0

#: The drift's interval and test (campaign.measure.drift): a 95 % confidence region of the
#: velocity, and "significant" when it leaves out 0, so a drift-free cell is called drifting in
#: 1 run of 20 by chance (the issue's bar: at most 1 of 20 seeds).
DRIFT_ALPHA = 0.05

#: ... the residual scatter of the drift fit gets this σ (m) added in quadrature: a noise-free
#: cell (simulated, `sim.noise_m: 0`) leaves residuals of round-off only, and a velocity of
#: round-off would otherwise test as significant; 1 nm is 1000 times below a tracker's noise.
DRIFT_NUMERICAL_SIGMA_M = 1e-9

#: Two measurements are of one pose when every joint but the last agrees exactly and the last
#: within this (rad): `campaign auto` re-measures a pose with its last joint r µrad on (r the
#: repeat, campaign.plan.extend.REMEASURE_OFFSET_RAD), a tool offset of 0.2 m then moves by
#: 2 µm at r = 10, below a tracker's noise; poses a plan chooses differ by 1e-3 rad or more.
SAME_POSE_TOL_RAD = 1e-5

#: The driver's drift check warns that the reference pose moved when its reading lies farther
#: from the mean of the reference's earlier readings than the noise floor explains with this
#: probability per check (campaign.measure.drift.moved_threshold_m): 8 checks a campaign then
#: warn falsely in under 1 % of campaigns, and a 10 µm tracker (σ ~6 µm of the tool position)
#: is warned at ~35 µm, a 100 µm one at ~0.35 mm (a fixed 0.05 mm warned at every check).
DRIFT_WARNING_ALPHA = 1e-3

#: ... and before any noise is known (no back-to-back repeats measured yet, no stated tracker
#: noise), at this fixed distance (mm): the default of the days before the floor decided it,
#: five times a 10 µm tracker's noise of the tool position.
DRIFT_WARNING_FALLBACK_MM = 0.05

#: Identifiability on the training poses (campaign.identify.identifiability): a direction of the
#: column-scaled whitened Jacobian whose singular value is below this fraction of the largest is
#: not identified. A joint that never moved gives round-off (1e-16 from an SVD of J, about 1e-8 from
#: the eigenvalues of JᵀJ, which campaign.identify.identifiability uses); a campaign of 12 random
#: poses on the COMAU has its smallest at 0.04, a wrist turned 1° 7e-4: the gap is five decades wide.
IDENT_NULL_RTOL = 1e-6

#: ... and below this fraction barely identified: its σ is at least 300 times the best-known
#: direction's (a wrist that turned 1-2°), where random 12-300 pose campaigns stay above 0.03.
IDENT_WEAK_RTOL = 3e-3

#: A joint whose training values span less than this (rad; m for a prismatic joint) never moved:
#: 0.1° is below any deliberate motion of a calibration campaign and above encoder noise.
JOINT_STILL_RAD = 1.7e-3

#: A joint whose training values span less than this fraction of its range is named beside barely
#: identified directions (a wrist that turned 1-3° of 400°): the likely cause, said in words.
JOINT_NARROW_FRACTION = 0.05

#: The calibrated domain (campaign.identify.domain). Margin beyond a joint's training range: this
#: many times range / n (a fresh pose from the same spread falls beyond n poses' extreme by more
#: than c·range/n with probability about exp(-c): 6 gives 0.25 % an end, 3 % over 6 joints' 12 ends)
DOMAIN_MARGIN_POSES = 6.0

#: ... and at least this (rad; 0.5°: a joint held still within encoder play is still inside) or,
#: for a prismatic joint, this (m)
DOMAIN_MIN_MARGIN_RAD = 8.7e-3
DOMAIN_MIN_MARGIN_M = 1e-3

#: Bins of a joint's limit range for its coverage (the share of bins holding a training pose)
DOMAIN_COVERAGE_BINS = 20

#: A pose is outside when, in some pair of joints, it lies outside the convex hull of the training
#: poses and farther from every one than this times the largest nearest-neighbour distance among them
#: (ranges scaled to 1). On uniform spreads of the COMAU (15 pairs, 8 seeds): 1.0 flags 8 % of fresh
#: poses at 80 training poses (17 % at worst), 1.2 3 %, 1.5 0.4 % (1.4 % at worst); a corner of joints
#: 1-2 (35 % x 35 %) no pose reached is flagged for a quarter of its poses at 80, 40 % at 240, half at 800
DOMAIN_PAIR_FACTOR = 1.5

#: ... from this many training poses on (below, a pair's nearest-neighbour distances scatter too
#: much: at 48 poses 1.4 flags 6 % of fresh poses at worst, at 16 even 1.6 flags 10 %)
DOMAIN_PAIR_MIN_POSES = 60

#: A relation the training poses kept among joints (q2 + q3 constant): a direction of the joint space,
#: ranges scaled by their spread, along which they spread less than this share of their widest, from
#: DOMAIN_RELATION_EXTRA_POSES poses more than joints on (random poses of the COMAU, Panda and TIAGo,
#: 1000 seeds each: at N + 2 poses 4-15 of them keep such a direction by chance, at N + 3 0-2, at N + 4
#: none; a joint turned 2° of 200° beside the others is 0.01, and a range of its own): a pose off it by
#: more than its training spread plus DOMAIN_MIN_MARGIN_RAD a joint is outside
DOMAIN_RELATION_RTOL = 0.01
DOMAIN_RELATION_EXTRA_POSES = 4

#: The tool point's nominal position rows leave what the measured points see by this share of their
#: norm or more (two reflectors: 0.01, the rotation about their line; three: 1e-15, round-off): the
#: tolerances in the unseen directions are part of sigma_mm (campaign.identify.uncertainty)
UNSEEN_TOOL_RTOL = 1e-6

#: `compensate --program`: the largest joint step (rad; m for a prismatic joint) a target's correction
#: may take and be written. Corrections are of the size of the robot's errors (the paper's Table 4:
#: joint offsets of up to about 1°, tool errors of about 1.6°), amplified for the wrist's outer
#: joints near its singularity (joint 4 by 12.7° at q5 = 16° in tests/test_program_compensate.py,
#: joint 6 turning back as much); another configuration differs by far more (a wrist flip by 180°,
#: the shoulder beside its singularity swung joint 1 by 44°), and the program's clearances were
#: planned for the written joints. It also bounds the solver's last iterate written for a target the
#: model does not reach exactly (never farther from it than the written joints: the solver takes
#: only improving steps)
PROGRAM_BEST_EFFORT_STEP_RAD = 0.52

#: A tracker's beam ends at the surface of the reflector's sphere (a 1.5" spherically mounted
#: reflector, 19.05 mm radius; the MuJoCo twin's nest_radius_m): the plan checks the robot's links
#: (the last link, the hand and fingers beyond the tool frame too) against the beam from there on,
#: as the twin's ray meets them; the nest and the tool right around the sphere lie within it.
REFLECTOR_RADIUS_M = 0.01905

#: A row of a measured-pose file without pose_id is the planned pose whose joints (rad; m for a
#: prismatic joint) all lie within this of its own: the commanded joints are the plan's as a
#: controller writes them (4 decimals in degrees: 1e-6 rad; 3 decimals of KRL, 1e-5 rad; a
#: reading of the encoders, ~1e-5 rad), while the plan's grid puts its poses 0.1 rad apart or more
PLAN_MATCH_TOL_RAD = 1e-3

# -- joint-indexed effects (campaign/effects/gravity.py, campaign/diagnose/joints.py) --

#: A joint carries a gravity-load effect by default (joint compliance, backlash) when its RMS
#: gravity torque over the workspace is at least this share of the most loaded joint's: the
#: COMAU Racer5's wrist joint 5 (2.6 %) carries the tool's weight on a lever, its joint 4
#: (1.3 %) and joint 6 (0.4 %) barely any; the Panda's joints 5 and 6 (4-6 %) carry its hand.
#: Diagnose searches every joint whatever this default (the default only fills a bare name).
GRAVITY_JOINT_MIN_SHARE = 0.02

#: The simulator draws a hidden effect's typical size from the tool point's displacement; a
#: parameter that moves the tool point less than this share of what it moves the reflectors
#: (a turn about the tool's own origin: round-off, 1e-17 m) is sized by the reflectors instead.
#: Before, a joint-6 offset of the UR3 (tool0 on joint 6's axis) was drawn as 3e290 rad.
SIM_UNMOVED_RTOL = 1e-6

#: A gravity torque at most this share of the arm's weight times 1 m (N·m) is the round-off of
#: Pinocchio's recursion, and is 0: a joint whose axis lies along gravity (a vertical joint 1)
#: carries ~1e-14 N·m of it, to which a compliance or backlash of that joint was fitted
#: (c1 = -2.1e9 rad/(N·m), σ 1.5e-20) instead of being held at 0 as not identifiable. The
#: smallest real torque of the arms known here (the Z1's joint 6) is 7e-3 N·m, 1e9 times more.
GRAVITY_TORQUE_ROUND_OFF = 1e-12

#: Poses over which a robot's default loaded joints are judged (random, inside the limits):
#: the RMS torque of each joint is known to a few per cent from 200.
GRAVITY_JOINT_POSES = 200

# -- diagnose: what earns a round, time told from pose (campaign/diagnose/) --

#: A round of poses (auto) is spent on structure only when the model-free test calls it
#: significant and it predicts at least this share of the held-out error: below it, what is
#: left is the noise's own sampling error or an effect too small to pay for hours of measuring
#: (the issue-31 runs spent 30 poses on "0 % of the held-out error (p = 0.078)").
MIN_ROUND_SHARE = 0.05

#: A run measured on more than one cell (campaign.identify.cells): a segment disagrees with the
#: others beyond its registration when the one-sided test of its held-out errors (one model against
#: it alone) has p below this (Bonferroni over the segments tested): the same level as diagnose's
#: candidates, a refusal costs the user a choice, a wrong mix costs them the calibration.
CELL_AGREEMENT_ALPHA = 0.01
#: ... and its held-out mean under one model exceeds the other by more than this share: with many
#: poses a test finds a few % of region-dependent structure (an effect the model lacks, fitted by a
#: segment's own model on its part of the workspace); two robots' geometric errors differ by
#: millimetres, many times the model's error.
CELL_AGREEMENT_MARGIN = 0.25
#: Folds of the agreement test (within each segment).
CELL_FOLDS = 5
#: Training poses a segment needs for its registration (six unknowns; three positions not in a line).
CELL_MIN_REGISTRATION_POSES = 3

#: The test set against the folds (campaign.diagnose.testset): the current model does not hold on
#: the test poses when their mean position error exceeds the folds' held-out mean with one-sided
#: p below TEST_SET_ALPHA (diagnose's own level) and by more than TEST_SET_MARGIN (a material
#: share: a correct model's test and fold errors are both the noise, a ratio near 1; a wrist
#: run-out hidden by training poses that hold q5 at ±0.855 rad gave 6.5×).
TEST_SET_ALPHA = 0.01
TEST_SET_MARGIN = 0.5
#: A joint is sparse when the test poses lie a median of more than this share of its range from
#: every training value of it (two training values over the range: about 25 %; 160 spread
#: training poses: well under 1 %).
TEST_SET_GAP_SHARE = 0.05
