"""The paper's residual compensator (section 5) as an estimator: joint coordinates -> residual.

Architecture: N inputs (the robot's joint coordinates), two tanh hidden layers (N1, N2), 6
linear outputs (the residual Δz = (Δt, Δφ) after a kinematic model), or 3 (Δt only) for
position-only data. Inputs are mapped to mean 0 / variance 1 with the joint limits (a uniform
distribution over eq. 17's ranges); targets to mean 0 / variance 1 on the training set (paper
5.1).

:class:`ResidualNetwork` holds the hyperparameters and, after ``fit``, what was learned (names
ending in ``_``); the training is Bayesian-regularised Levenberg-Marquardt from
:mod:`campaign.ann.lm`, whose solver strategies (matrix-free CG with K-FAC, or the full-Jacobian
reference) keep their scratch state in a workspace of their own. The network's description and
its structured Jacobian products are :class:`campaign.ann.mlp.MLP`.
"""

from __future__ import annotations

import numpy as np
import torch

from campaign.ann.lm import FullSolver, LMOptions, MatrixFreeSolver, br_update, train_lm
from campaign.ann.mlp import MLP, Mapping, joint_limits, joint_mapping, torch_threads
from campaign.errors import ConfigError, DataError, NotFittedError

__all__ = ["ResidualNetwork", "MLP", "Mapping", "joint_mapping", "br_update"]

#: the saved formats: /1 one network, /2 an ensemble (weights (K, N_w), target mappings (K, N_out))
FORMATS = ("campaign.ResidualNetwork/1", "campaign.ResidualNetwork/2")


class ResidualNetwork:
    """The paper's residual compensator: q (rad) -> Δz (m, rad), trained with Bayesian regularisation.

    Parameters
    ----------
    hidden : (N1, N2) hidden layer sizes
    q_lower, q_upper : joint limits (N,) each (rad, m for prismatic joints) for the input mapping;
        None: the embedded default robot's (6 joints; other robots must give theirs)
    max_epochs : LM epochs at most (the paper: 2048)
    solver : "cg" (matrix-free, default) or "full" (explicit Jacobian, the reference)
    gamma_every : epochs between re-estimates of α, β, γ
    probes : Hutchinson probes for tr(H⁻¹) (cg solver)
    cg_maxiter : conjugate-gradient iterations per LM step at most
    cg_miniter, cg_ramp_epochs : optionally start with cg_miniter iterations per step, rising
        linearly to cg_maxiter at epoch cg_ramp_epochs (None: cg_maxiter throughout)
    cg_tol : CG stops early when ‖r‖ ≤ cg_tol ‖b‖
    trace_maxiter : CG iterations per Hutchinson probe at most (warm-started from the last estimate)
    preconditioner : "kfac" (block-diagonal Kronecker factors of JᵀJ, default) or "jacobi"
        (its exact diagonal)
    product_dtype : precision of the Jacobian products inside CG ("float32" or "float64"); weights,
        gradient, errors and the objective are always float64
    min_rel_improvement, patience : converged when an LM step lowers F by less than this fraction
        for ``patience`` epochs in a row
    window, window_rtol : plateau: stop when the training MSE fell by less than ``window_rtol``
        (relative) over the last ``window`` epochs and γ moved by less than 10 × that
    seed : initialisation seed (weights and Hutchinson probes); training is deterministic
    n_threads : torch intra-op threads during fit/predict (None: leave torch's setting). Default 1:
        on the shared 2-core machine 2 threads were 3-10× slower whenever another process ran
        (OpenMP threads waiting for a busy core; docs/ann.md)
    cg_warm_start : start each LM step's CG at the previous accepted step
    progress : optional callable(epoch=, max_epochs=, mse=, gamma=) every ``progress_every`` epochs
    """

    def __init__(self, *, hidden=(64, 32), q_lower=None, q_upper=None, max_epochs=2048, solver="cg",
                 gamma_every=20, probes=4, cg_maxiter=20, product_dtype="float32", seed=0,
                 min_rel_improvement=1e-5, patience=15, window=50, window_rtol=1e-2, mu_max=1e10,
                 n_threads=1, cg_warm_start=False, progress=None, progress_every=10,
                 preconditioner="kfac", cg_tol=1e-3, cg_miniter=None, cg_ramp_epochs=100, trace_maxiter=20):
        self.hidden = hidden
        self.cg_miniter = cg_miniter
        self.cg_ramp_epochs = cg_ramp_epochs
        self.trace_maxiter = trace_maxiter
        self.preconditioner = preconditioner
        self.cg_tol = cg_tol
        self.q_lower = q_lower
        self.q_upper = q_upper
        self.max_epochs = max_epochs
        self.solver = solver
        self.gamma_every = gamma_every
        self.probes = probes
        self.cg_maxiter = cg_maxiter
        self.product_dtype = product_dtype
        self.seed = seed
        self.min_rel_improvement = min_rel_improvement
        self.patience = patience
        self.window = window
        self.window_rtol = window_rtol
        self.mu_max = mu_max
        self.n_threads = n_threads
        self.cg_warm_start = cg_warm_start
        self.progress = progress
        self.progress_every = progress_every

    # -- fitting ----------------------------------------------------------------------------
    def fit(self, q, dz):
        """Train on joint coordinates q (n, N) (rad, m) and residuals dz (n, 6) (m, rad), or
        dz (n, 3) (m) for position-only data."""
        q = np.asarray(q, dtype=float)
        dz = np.asarray(dz, dtype=float)
        if q.ndim != 2 or q.shape[1] < 1 or dz.ndim != 2 or dz.shape[0] != len(q) or dz.shape[1] not in (3, 6):
            raise DataError(f"ResidualNetwork.fit: expected q (n, N) and dz (n, 6) or (n, 3), got {q.shape}, "
                            f"{dz.shape}")
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(dz))):
            raise DataError("ResidualNetwork.fit: q and dz must be finite")
        strategy = self._strategy()
        dtype = torch.float64
        lo, hi = joint_limits(self.q_lower, self.q_upper, q.shape[1])
        self.input_mapping_ = joint_mapping(lo, hi)
        std = dz.std(axis=0)
        self.target_mapping_ = Mapping(dz.mean(axis=0), np.where(std > 0, std, 1.0))
        x = torch.as_tensor(self.input_mapping_.apply(q), dtype=dtype)
        t = torch.as_tensor(self.target_mapping_.apply(dz), dtype=dtype)
        self.net_ = MLP(q.shape[1], tuple(self.hidden), dz.shape[1])
        gen = torch.Generator().manual_seed(int(self.seed))
        w = self.net_.init(gen, dtype)
        options = LMOptions(max_epochs=self.max_epochs, gamma_every=self.gamma_every,
                            min_rel_improvement=self.min_rel_improvement, patience=self.patience,
                            window=self.window, window_rtol=self.window_rtol, mu_max=self.mu_max)
        with torch_threads(self.n_threads):
            result = train_lm(self.net_, w, x, t, strategy, gen, options=options, progress=self.progress,
                              progress_every=self.progress_every)
        self.weights_ = result.weights
        self.alpha_, self.beta_, self.gamma_ = result.alpha, result.beta, result.gamma
        self.switched_off_ = False
        self.n_epochs_ = result.n_epochs
        self.stop_reason_ = result.stop_reason
        self.mse_normalised_ = result.mse_normalised
        self.E_D_, self.E_W_ = result.E_D, result.E_W
        self.loss_ = result.loss
        self.loss_history_ = result.history  # columns: epoch, normalised MSE, γ, α, β
        self.cg_iterations_ = result.cg_iterations
        return self

    def _strategy(self):
        """The solver strategy of these hyperparameters (campaign.ann.lm), checked."""
        if self.solver not in ("cg", "full"):
            raise ConfigError(f"solver must be 'cg' or 'full', not {self.solver!r}")
        if self.preconditioner not in ("kfac", "jacobi"):
            raise ConfigError(f"preconditioner must be 'kfac' or 'jacobi', not {self.preconditioner!r}")
        if self.product_dtype not in ("float32", "float64"):
            raise ConfigError(f"product_dtype must be 'float32' or 'float64', not {self.product_dtype!r}")
        if self.solver == "full":
            return FullSolver()
        return MatrixFreeSolver(preconditioner=self.preconditioner, product_dtype=self.product_dtype,
                                cg_maxiter=self.cg_maxiter, cg_miniter=self.cg_miniter,
                                cg_ramp_epochs=self.cg_ramp_epochs, cg_tol=self.cg_tol, probes=self.probes,
                                trace_maxiter=self.trace_maxiter, warm_start=self.cg_warm_start)

    # -- use --------------------------------------------------------------------------------
    def _check(self):
        if not hasattr(self, "weights_"):
            raise NotFittedError("ResidualNetwork is not fitted; call fit() first")

    @property
    def n_inputs_(self) -> int:
        """Joint values per pose the network takes (N)."""
        self._check()
        return self.net_.n_in

    @property
    def n_outputs_(self) -> int:
        """6 (Δt, Δφ) or 3 (Δt only: trained on position-only data)."""
        self._check()
        return self.net_.n_out

    def predict(self, q) -> np.ndarray:
        """Predicted residual Δz (n, 6) (m, rad), or Δt (n, 3) (m) for a network trained on
        position-only data, for joint coordinates q (n, N) (rad, m).

        For an ensemble (weights_ of shape (K, N_w), see :meth:`from_members`) the mean of the
        K members' predictions, each mapped back with its own target mapping.
        """
        members = self.predict_members(q)
        out = 0.0
        for y in members:
            out = out + y
        return out / len(members)

    def predict_members(self, q) -> np.ndarray:
        """(K, n, N_out): each member's predicted residual (K = 1 for a single network), the
        cross-validation members' spread for an ensemble (campaign.identify.uncertainty)."""
        self._check()
        q = np.asarray(q, dtype=float)
        if q.shape[-1] != self.net_.n_in:
            raise DataError(f"ResidualNetwork.predict: the network takes {self.net_.n_in} joint values per pose, "
                            f"got q of shape {q.shape}")
        x = torch.as_tensor(self.input_mapping_.apply(q.reshape(-1, self.net_.n_in)), dtype=self.weights_.dtype)
        W = self.weights_ if self.weights_.ndim == 2 else self.weights_[None]
        mean = np.asarray(self.target_mapping_.mean, dtype=float).reshape(len(W), -1)
        scale = np.asarray(self.target_mapping_.scale, dtype=float).reshape(len(W), -1)
        out = []
        with torch.no_grad(), torch_threads(getattr(self, "n_threads", None)):
            for w, mu, sd in zip(W, mean, scale):
                y, _ = self.net_.forward(w, x)
                out.append(y.cpu().numpy().astype(float) * sd + mu)
        return np.stack(out)

    @classmethod
    def from_members(cls, hidden, weights, input_mapping: Mapping, target_means, target_scales,
                     **attributes) -> "ResidualNetwork":
        """A fitted network from trained weights: one member (weights (N_w,), target mapping
        (N_out,)) or an ensemble whose prediction is the members' mean (weights (K, N_w), mappings
        (K, N_out)). The input mapping's length gives N (joint values), the target mapping's last
        axis N_out (6, or 3 for position-only data).
        attributes: fitted-state values to set (e.g. ``alpha_``, ``n_epochs_``)."""
        net = cls(hidden=tuple(int(h) for h in hidden))
        means, scales = np.asarray(target_means, dtype=float), np.asarray(target_scales, dtype=float)
        net.net_ = _mlp(net.hidden, input_mapping, means, scales)
        w = torch.as_tensor(np.asarray(weights, dtype=float))
        if w.shape[-1] != net.net_.n_weights or w.ndim not in (1, 2) or means.shape[:-1] != w.shape[:-1]:
            raise DataError(f"weights of shape {tuple(w.shape)} and target mappings of shape {means.shape} do not "
                            f"fit a {net.net_.n_in}-{net.hidden[0]}-{net.hidden[1]}-{net.net_.n_out} network")
        net.weights_ = w
        net.input_mapping_ = input_mapping
        net.target_mapping_ = Mapping(means, scales)
        net.alpha_ = net.beta_ = net.gamma_ = float("nan")
        net.n_epochs_ = 0
        net.switched_off_ = False
        for k, v in attributes.items():
            setattr(net, k, v)
        return net

    # -- safe persistence: tensors and plain values only, loaded with weights_only=True ---------
    def save(self, path) -> None:
        """Write the fitted network (format in docs/ann.md: tensors and plain numbers only; N and
        N_out are the lengths of the input and target mappings)."""
        self._check()
        state = {
            "format": FORMATS[1] if self.weights_.ndim == 2 else FORMATS[0],
            "hidden": torch.tensor(list(self.hidden), dtype=torch.int64),
            "weights": self.weights_.detach().cpu().clone(),
            "input_mean": torch.tensor(self.input_mapping_.mean), "input_scale": torch.tensor(self.input_mapping_.scale),
            "target_mean": torch.tensor(self.target_mapping_.mean),
            "target_scale": torch.tensor(self.target_mapping_.scale),
            "alpha": self.alpha_, "beta": self.beta_, "gamma": self.gamma_, "n_epochs": self.n_epochs_,
            "switched_off": bool(getattr(self, "switched_off_", False)),
        }
        torch.save(state, str(path))

    @classmethod
    def load(cls, path) -> "ResidualNetwork":
        """Read a network written by :meth:`save` (``torch.load(..., weights_only=True)``: no
        pickled objects), its shapes checked against each other."""
        try:
            state = torch.load(str(path), weights_only=True, map_location="cpu")
        except Exception as exc:  # torch raises several types for a bad file
            raise DataError(f"{path}: not a saved residual network ({exc.__class__.__name__})") from None
        if not isinstance(state, dict) or state.get("format") not in FORMATS:
            raise DataError(f"{path}: not a saved residual network (unknown format)")
        try:
            hidden = tuple(int(v) for v in state["hidden"])
            mapping = Mapping(state["input_mean"].numpy(), state["input_scale"].numpy())
            means, scales = state["target_mean"].numpy(), state["target_scale"].numpy()
            weights = state["weights"]
            attrs = dict(alpha_=float(state["alpha"]), beta_=float(state["beta"]), gamma_=float(state["gamma"]),
                         n_epochs_=int(state["n_epochs"]), switched_off_=bool(state.get("switched_off", False)))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise DataError(f"{path}: malformed residual network ({exc.__class__.__name__}: {exc})") from None
        if len(hidden) != 2 or mapping.mean.ndim != 1 or mapping.mean.shape != mapping.scale.shape \
                or means.shape != scales.shape or means.ndim < 1 or means.shape[-1] not in (3, 6) \
                or weights.ndim != (2 if state["format"] == FORMATS[1] else 1):
            raise DataError(f"{path}: weights and mappings of a residual network do not fit each other")
        net = cls(hidden=hidden)
        net.net_ = _mlp(hidden, mapping, means, scales)
        if weights.shape[-1] != net.net_.n_weights or means.shape[:-1] != weights.shape[:-1]:
            raise DataError(f"{path}: weights do not match hidden sizes {hidden} with {net.net_.n_in} inputs and "
                            f"{net.net_.n_out} outputs")
        net.weights_ = weights
        net.input_mapping_ = mapping
        net.target_mapping_ = Mapping(means, scales)
        for k, v in attrs.items():
            setattr(net, k, v)
        return net


def _mlp(hidden, input_mapping: Mapping, target_means, target_scales) -> MLP:
    """The network shape of these mappings: N inputs, N_out outputs."""
    return MLP(len(np.atleast_1d(input_mapping.mean)), tuple(int(h) for h in hidden),
               int(np.shape(target_means)[-1]))
