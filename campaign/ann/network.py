"""The residual network of the paper's section 5, trained with Bayesian regularisation.

Architecture: 6 inputs (joint coordinates), two tanh hidden layers (N1, N2), 6 linear
outputs (the residual Δz after a kinematic model). Inputs are mapped to mean 0 / variance 1
with the joint limits (a uniform distribution over eq. 17's ranges); targets to mean 0 /
variance 1 on the training set (paper 5.1).

Training minimises ``F = β E_D + α E_W`` (MacKay 1992; Foresee & Hagan 1997) with
Levenberg-Marquardt steps on the Gauss-Newton Hessian ``H = 2β JᵀJ + 2α I``, re-estimating
``γ = N_w − 2α tr(H⁻¹)``, ``α = γ / (2 E_W)``, ``β = (N_d − γ) / (2 E_D)`` as training goes.

Speed (docs/ann.md has the measurements): J is never formed. For a two-layer tanh net the
products ``J v`` and ``Jᵀ u`` are a handful of small matrix products (written out below,
checked against torch.func in the tests), so each LM step is solved by conjugate gradients
(float32 products, float64 everything else) preconditioned with a block-diagonal Kronecker
(K-FAC) approximation of JᵀJ whose damped inverse is exact and cheap by eigendecomposition of
the small factors; tr(H⁻¹) by a Hutchinson estimate with the same solver and the
preconditioner's exact trace as a control variate. A plain full-Jacobian LM
(``solver="full"``: JᵀJ assembled exactly in float64 by :meth:`MLP.gauss_newton`, Cholesky
solves, exact trace) is kept as the reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from campaign.errors import ConfigError, DataError, NotFittedError


@dataclass(frozen=True)
class Mapping:
    """Affine normalisation ``(x - mean) / scale`` per column."""

    mean: np.ndarray
    scale: np.ndarray

    def apply(self, x):
        return (np.asarray(x, dtype=float) - self.mean) / self.scale

    def invert(self, y):
        return np.asarray(y, dtype=float) * self.scale + self.mean


def joint_mapping(q_lower, q_upper) -> Mapping:
    """Mean 0 / variance 1 for joint values uniformly distributed over their limits."""
    lo, hi = np.asarray(q_lower, dtype=float), np.asarray(q_upper, dtype=float)
    return Mapping(0.5 * (lo + hi), (hi - lo) / math.sqrt(12.0))


# -- the network as flat parameters, with structured Jacobian products -----------------------

class MLP:
    """Shapes and slicing of the flat parameter vector w = (W1, b1, W2, b2, W3, b3)."""

    def __init__(self, n_in: int, hidden: tuple, n_out: int):
        self.n_in, self.n1, self.n2, self.n_out = n_in, int(hidden[0]), int(hidden[1]), n_out
        shapes = [(self.n1, n_in), (self.n1,), (self.n2, self.n1), (self.n2,), (n_out, self.n2), (n_out,)]
        self.shapes = shapes
        self.sizes = [int(np.prod(s)) for s in shapes]
        self.n_weights = sum(self.sizes)

    def unpack(self, w):
        if isinstance(w, (tuple, list)):  # already unpacked
            return w
        out, i = [], 0
        for s, n in zip(self.shapes, self.sizes):
            out.append(w[i : i + n].view(s))
            i += n
        return out

    def init(self, generator, dtype):
        """Nguyen-Widrow-like uniform initialisation (tanh layers), zero output layer bias."""
        parts = []
        for s in self.shapes:
            fan_in = s[1] if len(s) == 2 else 1
            bound = 1.0 / math.sqrt(fan_in) if len(s) == 2 else 0.5
            parts.append((torch.rand(s, generator=generator, dtype=dtype) * 2 - 1).reshape(-1) * bound)
        parts[-1].zero_()
        return torch.cat(parts)

    def forward(self, w, x):
        W1, b1, W2, b2, W3, b3 = self.unpack(w)
        h1 = torch.tanh(x @ W1.T + b1)
        h2 = torch.tanh(h1 @ W2.T + b2)
        return h2 @ W3.T + b3, (h1, h2)

    def jvp(self, w, x, cache, v):
        """J v: (n, n_out), the change of the outputs along parameter direction v."""
        W1, b1, W2, b2, W3, b3 = self.unpack(w)
        dW1, db1, dW2, db2, dW3, db3 = self.unpack(v)
        h1, h2 = cache
        dh1 = (1 - h1 * h1) * (x @ dW1.T + db1)
        dh2 = (1 - h2 * h2) * (dh1 @ W2.T + h1 @ dW2.T + db2)
        return dh2 @ W3.T + h2 @ dW3.T + db3

    def vjp(self, w, x, cache, u):
        """Jᵀ u: (n_weights,), for output cotangents u (n, n_out)."""
        W1, b1, W2, b2, W3, b3 = self.unpack(w)
        h1, h2 = cache
        g_a2 = (u @ W3) * (1 - h2 * h2)
        g_a1 = (g_a2 @ W2) * (1 - h1 * h1)
        return torch.cat([(g_a1.T @ x).reshape(-1), g_a1.sum(0), (g_a2.T @ h1).reshape(-1), g_a2.sum(0),
                          (u.T @ h2).reshape(-1), u.sum(0)])

    def jtj_diagonal(self, w, x, cache):
        """diag(JᵀJ) (n_weights,), exactly, without forming J."""
        W1, b1, W2, b2, W3, b3 = self.unpack(w)
        h1, h2 = cache
        n = x.shape[0]
        s2 = 1 - h2 * h2  # (n, n2)
        s1 = 1 - h1 * h1
        # per output k: g_a2[k] = W3[k] * s2  -> (n, k, n2); g_a1[k] = (g_a2[k] @ W2) * s1
        g_a2 = W3[None, :, :] * s2[:, None, :]
        g_a1 = (g_a2 @ W2) * s1[:, None, :]
        q1 = (g_a1 * g_a1).sum(1)  # (n, n1): Σ_k g_a1²
        q2 = (g_a2 * g_a2).sum(1)
        return torch.cat([(q1.T @ (x * x)).reshape(-1), q1.sum(0), (q2.T @ (h1 * h1)).reshape(-1), q2.sum(0),
                          ((h2 * h2).sum(0)[None, :].expand(self.n_out, -1)).reshape(-1),
                          torch.full((self.n_out,), float(n), dtype=x.dtype)])

    def kfac(self, w, x, cache, max_samples=4096):
        """Kronecker factors of the per-layer diagonal blocks of JᵀJ, eigendecomposed.

        Layer l's parameters (W_l | b_l) as a matrix V (r × (c+1)); each row of J restricted to
        that block is ``a ⊗ x̃`` (a: the output-k cotangent at the layer's pre-activation, x̃ =
        (layer input, 1)), so the block is ``Σ_s Σ_k (a aᵀ) ⊗ (x̃ x̃ᵀ)``, approximated (K-FAC,
        Martens & Grosse 2015) by ``(Σ a aᵀ / n) ⊗ (Σ x̃ x̃ᵀ)``, exact for the output layer.
        The first layer's A factor is estimated on at most ``max_samples`` samples (it is only a
        preconditioner). Returns [(λ_A, Q_A, λ_B, Q_B)] per layer.
        """
        W1, b1, W2, b2, W3, b3 = self.unpack(w)
        h1, h2 = cache
        n = x.shape[0]
        s2 = 1 - h2 * h2
        # layer 2: a[k] = W3[k] ∘ s2, so Σ_s Σ_k a aᵀ = (W3ᵀW3) ∘ (s2ᵀ s2)
        A2 = (W3.T @ W3) * (s2.T @ s2)
        # layer 1: a[k] = (W3[k] ∘ s2) W2 ∘ s1, one (n·n_out, n2) @ (n2, n1) product; the costliest
        # factor, so estimated on an evenly strided subset of at most max_samples samples
        sub = slice(None, None, max(1, -(-n // max_samples)))
        m = s2[sub].shape[0]
        g_a1 = ((W3[None, :, :] * s2[sub][:, None, :]).reshape(-1, self.n2) @ W2).reshape(m, self.n_out, self.n1)
        g_a1 = (g_a1 * (1 - h1[sub] * h1[sub])[:, None, :]).reshape(-1, self.n1)
        A1 = (g_a1.T @ g_a1) * (n / m)
        one = torch.ones((n, 1), dtype=x.dtype)
        pairs = []
        for A, inp in ((A1, x), (A2, h1), (None, h2)):
            xt = torch.cat([inp, one], 1)
            lb, Qb = torch.linalg.eigh((xt.T @ xt).double())
            if A is None:  # output layer: Σ_k e_k e_kᵀ / n · n = I, exact
                la, Qa = torch.ones(self.n_out, dtype=torch.float64), torch.eye(self.n_out, dtype=torch.float64)
            else:
                la, Qa = torch.linalg.eigh(A.double() / n)
            pairs.append((la.clamp_min(0).to(x.dtype), Qa.to(x.dtype), lb.clamp_min(0).to(x.dtype), Qb.to(x.dtype)))
        return pairs

    def kfac_inverse(self, factors, scale, shift):
        """The map v -> (scale · K + shift I)⁻¹ v for the block-diagonal Kronecker approximation K
        of JᵀJ (:meth:`kfac`): per layer ``Q_A [(Q_Aᵀ V Q_B) / (scale λ_A λ_Bᵀ + shift)] Q_Bᵀ``."""
        blocks = [(Qa, Qb, 1.0 / (scale * la[:, None] * lb[None, :] + shift)) for la, Qa, lb, Qb in factors]

        def solve(v):
            parts = self.unpack(v)
            out = []
            for (Qa, Qb, D), dW, db in zip(blocks, parts[0::2], parts[1::2]):
                V = Qa @ (((Qa.T @ torch.cat([dW, db[:, None]], 1)) @ Qb) * D) @ Qb.T
                out += [V[:, :-1].reshape(-1), V[:, -1]]
            return torch.cat(out)
        return solve

    def kfac_solve(self, factors, v, scale, shift):
        """(scale · K + shift I)⁻¹ v, see :meth:`kfac_inverse`."""
        return self.kfac_inverse(factors, scale, shift)(v)

    def gauss_newton(self, w, x, cache, chunk=1000):
        """JᵀJ (n_weights, n_weights) assembled exactly, in x's precision, without forming J.

        Layer l's block of a Jacobian row is ``a_l ⊗ x̃_l`` (see :meth:`kfac`), so block (l, m) of
        JᵀJ is ``Σ_s C_lm[s] ⊗ D_lm[s]`` with ``C_lm = Σ_k a_l[k] a_m[k]ᵀ`` and ``D_lm = x̃_l x̃_mᵀ``:
        one matrix product ``Cᵀ D`` over the samples per block pair, done in chunks of samples.
        About 7× fewer flops than ``J.T @ J`` for (64, 32) on 6 outputs. The reference solver's.
        """
        W1, b1, W2, b2, W3, b3 = self.unpack(w)
        h1, h2 = cache
        n, dt = x.shape[0], x.dtype
        rows = [self.n1, self.n2, self.n_out]
        cols = [self.n_in + 1, self.n1 + 1, self.n2 + 1]
        # flat index of each (i, j) of the layer matrix (W | b): W row-major, then b
        perm, off = [], 0
        for r, c in zip(rows, cols):
            i = torch.arange(r)[:, None]
            j = torch.arange(c)[None, :]
            perm.append((off + torch.where(j < c - 1, i * (c - 1) + j, r * (c - 1) + i)).reshape(-1))
            off += r * c
        G = torch.zeros((self.n_weights, self.n_weights), dtype=dt)
        for s0 in range(0, n, chunk):
            sl = slice(s0, min(n, s0 + chunk))
            m = sl.stop - sl.start
            one = torch.ones((m, 1), dtype=dt)
            g_a2 = W3[None, :, :] * (1 - h2[sl] * h2[sl])[:, None, :]
            g_a1 = (g_a2 @ W2) * (1 - h1[sl] * h1[sl])[:, None, :]
            a = [g_a1, g_a2, torch.eye(self.n_out, dtype=dt).expand(m, -1, -1)]
            xt = [torch.cat([x[sl], one], 1), torch.cat([h1[sl], one], 1), torch.cat([h2[sl], one], 1)]
            for l in range(3):
                for k in range(l, 3):
                    C = (a[l].transpose(1, 2) @ a[k]).reshape(m, -1)  # (m, r_l r_k)
                    D = (xt[l][:, :, None] * xt[k][:, None, :]).reshape(m, -1)  # (m, c_l c_k)
                    B = (C.T @ D).reshape(rows[l], rows[k], cols[l], cols[k]).permute(0, 2, 1, 3)
                    B = B.reshape(rows[l] * cols[l], rows[k] * cols[k])
                    G[perm[l][:, None], perm[k][None, :]] += B
                    if k != l:
                        G[perm[k][:, None], perm[l][None, :]] += B.T
        return G

    def jacobian(self, w, x):
        """The full Jacobian (n·n_out, n_weights), rows ordered sample-major. Reference only."""
        _, cache = self.forward(w, x)
        n = x.shape[0]
        rows = torch.empty((n, self.n_out, self.n_weights), dtype=x.dtype)
        for k in range(self.n_out):
            u = torch.zeros((n, self.n_out), dtype=x.dtype)
            u[:, k] = 1.0
            # per-sample gradients of output k: outer products per layer
            W1, b1, W2, b2, W3, b3 = self.unpack(w)
            h1, h2 = cache
            g_a2 = W3[k][None, :] * (1 - h2 * h2)
            g_a1 = (g_a2 @ W2) * (1 - h1 * h1)
            e = torch.zeros((n, self.n_out), dtype=x.dtype)
            e[:, k] = 1.0
            rows[:, k, :] = torch.cat([
                (g_a1[:, :, None] * x[:, None, :]).reshape(n, -1), g_a1,
                (g_a2[:, :, None] * h1[:, None, :]).reshape(n, -1), g_a2,
                (e[:, :, None] * h2[:, None, :]).reshape(n, -1), e], dim=1)
        return rows.reshape(n * self.n_out, self.n_weights)


# -- Bayesian regularisation -----------------------------------------------------------------

class _threads:
    """Context manager: torch intra-op threads set to n (None: unchanged), restored on exit."""

    def __init__(self, n):
        self.n = n

    def __enter__(self):
        self.before = torch.get_num_threads()
        if self.n is not None:
            torch.set_num_threads(int(self.n))

    def __exit__(self, *exc):
        torch.set_num_threads(self.before)


def br_update(gamma_trace_inv, n_weights, n_data, alpha, E_D, E_W):
    """One MacKay / Foresee-Hagan update: returns (gamma, alpha, beta).

    gamma_trace_inv: tr(H⁻¹) with H = 2β JᵀJ + 2α I at the current point.
    """
    gamma = n_weights - 2.0 * alpha * gamma_trace_inv
    gamma = float(min(max(gamma, 1e-6), n_weights))
    alpha = gamma / (2.0 * max(E_W, 1e-300))
    beta = (n_data - gamma) / (2.0 * max(E_D, 1e-300))
    return gamma, alpha, beta


def _pcg(apply_A, b, precond, x0=None, tol=1e-3, maxiter=50):
    """Preconditioned conjugate gradients for SPD A. Returns (x, iterations).

    precond: the preconditioner M⁻¹ as a callable r -> M⁻¹ r, or a tensor (Jacobi: r / precond).
    Stops when ‖r‖ ≤ tol ‖b‖ or after maxiter iterations.
    """
    M = precond if callable(precond) else (lambda r: r / precond)
    x = torch.zeros_like(b) if x0 is None else x0.clone()
    r = b - apply_A(x) if x0 is not None else b.clone()
    z = M(r)
    p = z.clone()
    rz = r @ z
    bnorm = torch.linalg.vector_norm(b)
    it = 0
    for it in range(1, maxiter + 1):
        Ap = apply_A(p)
        a = rz / (p @ Ap)
        x = x + a * p
        r = r - a * Ap
        if torch.linalg.vector_norm(r) <= tol * bnorm:
            break
        z = M(r)
        rz_new = r @ z
        p = z + (rz_new / rz) * p
        rz = rz_new
    return x, it


class ResidualNetwork:
    """The paper's residual compensator: q (rad) -> Δz (m, rad), trained with Bayesian regularisation.

    Parameters
    ----------
    hidden : (N1, N2) hidden layer sizes
    q_lower, q_upper : joint limits (rad) for the input mapping; None: taken from the data's range
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
        """Train on joint coordinates q (n, 6) rad and residuals dz (n, 6) (m, rad)."""
        q = np.asarray(q, dtype=float)
        dz = np.asarray(dz, dtype=float)
        if q.ndim != 2 or q.shape[1] != 6 or dz.shape != (len(q), 6):
            raise DataError(f"ResidualNetwork.fit: expected q (n, 6) and dz (n, 6), got {q.shape}, {dz.shape}")
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(dz))):
            raise DataError("ResidualNetwork.fit: q and dz must be finite")
        if self.solver not in ("cg", "full"):
            raise ConfigError(f"solver must be 'cg' or 'full', not {self.solver!r}")
        if self.preconditioner not in ("kfac", "jacobi"):
            raise ConfigError(f"preconditioner must be 'kfac' or 'jacobi', not {self.preconditioner!r}")
        dtype = torch.float64
        if self.product_dtype not in ("float32", "float64"):
            raise ConfigError(f"product_dtype must be 'float32' or 'float64', not {self.product_dtype!r}")
        if self.q_lower is None or self.q_upper is None:
            from campaign.model.robot import RobotModel

            robot = RobotModel.load()  # eq. 17's limits of the embedded default robot
        lo = np.asarray(robot.q_lower if self.q_lower is None else self.q_lower, dtype=float)
        hi = np.asarray(robot.q_upper if self.q_upper is None else self.q_upper, dtype=float)
        if lo.shape != (6,) or hi.shape != (6,) or not np.all(hi > lo):
            raise ConfigError(f"joint limits must be 6 values each with q_upper > q_lower, got {lo}, {hi}")
        self.input_mapping_ = joint_mapping(lo, hi)
        std = dz.std(axis=0)
        self.target_mapping_ = Mapping(dz.mean(axis=0), np.where(std > 0, std, 1.0))
        x = torch.as_tensor(self.input_mapping_.apply(q), dtype=dtype)
        t = torch.as_tensor(self.target_mapping_.apply(dz), dtype=dtype)
        self.net_ = MLP(6, tuple(self.hidden), 6)
        gen = torch.Generator().manual_seed(int(self.seed))
        w = self.net_.init(gen, dtype)
        self._probe_z = self._probe_s = None
        with _threads(self.n_threads):
            self._train(w, x, t, gen)
        return self

    def _train(self, w, x, t, gen):
        net = self.net_
        N = net.n_weights
        n_data = t.numel()
        full = self.solver == "full"
        pdt = torch.float32 if self.product_dtype == "float32" else torch.float64
        x_p = x.to(pdt)
        y, cache = net.forward(w, x)
        e = y - t
        E_D, E_W = float((e * e).sum()), float((w * w).sum())
        # MATLAB trainbr's start: γ = N, α and β from the current errors
        gamma = float(N)
        alpha = gamma / (2 * max(E_W, 1e-12))
        beta = (n_data - gamma) / (2 * max(E_D, 1e-12)) if n_data > gamma else n_data / (2 * max(E_D, 1e-12))
        mu = 5e-3
        history = []
        stall = 0
        delta = None
        epoch = 0
        stop = "max_epochs"
        self.cg_iterations_ = 0
        JtJ_next = None
        for epoch in range(1, self.max_epochs + 1):
            F = beta * E_D + alpha * E_W
            grad = 2 * beta * net.vjp(w, x, cache, e) + 2 * alpha * w
            if full:
                JtJ = JtJ_next if JtJ_next is not None else net.gauss_newton(w, x, cache)
                JtJ_next = None
                eye = torch.eye(N, dtype=x.dtype)
            else:
                w_p, cache_p = w.to(pdt), tuple(c.to(pdt) for c in cache)
                pre = self._preconditioner(w_p, x_p, cache_p, epoch)
            accepted = False
            while mu <= self.mu_max:
                if full:
                    L, info = torch.linalg.cholesky_ex(2 * beta * JtJ + (2 * alpha + mu) * eye)
                    if int(info) != 0:
                        mu *= 10
                        continue
                    step = -torch.cholesky_solve(grad[:, None], L)[:, 0]
                else:
                    step, its = _pcg(self._apply_H(w_p, x_p, cache_p, beta, 2 * alpha + mu), -grad,
                                     self._precond_solve(pre, beta, 2 * alpha + mu),
                                     x0=delta if self.cg_warm_start else None, tol=self.cg_tol,
                                     maxiter=self._cg_budget(epoch))
                    self.cg_iterations_ += its
                w_new = w + step
                y_new, cache_new = net.forward(w_new, x)
                e_new = y_new - t
                E_D_new, E_W_new = float((e_new * e_new).sum()), float((w_new * w_new).sum())
                F_new = beta * E_D_new + alpha * E_W_new
                if F_new < F:
                    accepted = True
                    break
                mu *= 10
                delta = None
            if not accepted:
                stop = "mu_max"
                break
            rel = (F - F_new) / max(F, 1e-300)
            delta = step
            w, cache, e, E_D, E_W = w_new, cache_new, e_new, E_D_new, E_W_new
            mu = max(mu / 10, 1e-20)
            if epoch % self.gamma_every == 0 or epoch == 1:
                if full:  # JᵀJ at the new point, reused by the next epoch's step
                    JtJ_next = net.gauss_newton(w, x, cache)
                tr_inv = self._trace_inverse(w, x, cache, alpha, beta, gen, JtJ_next if full else None)
                gamma, alpha, beta = br_update(tr_inv, N, n_data, alpha, E_D, E_W)
            history.append((epoch, E_D / n_data, gamma, alpha, beta))
            if self.progress is not None and (epoch % self.progress_every == 0 or epoch == 1):
                self.progress(epoch=epoch, max_epochs=self.max_epochs, mse=E_D / n_data, gamma=gamma)
            stall = stall + 1 if rel < self.min_rel_improvement else 0
            if stall >= self.patience:
                stop = "converged"
                break
            if self.window and epoch > self.window:
                _, mse_then, gamma_then, _, _ = history[-1 - self.window]
                mse_now = E_D / n_data
                if (mse_then - mse_now) < self.window_rtol * mse_now and \
                        abs(gamma - gamma_then) < 10 * self.window_rtol * gamma:
                    stop = "plateau"
                    break
        self.weights_ = w
        self.alpha_, self.beta_, self.gamma_ = float(alpha), float(beta), float(gamma)
        self.n_epochs_ = epoch
        self.stop_reason_ = stop
        self.mse_normalised_ = E_D / n_data
        self.E_D_, self.E_W_ = float(E_D), float(E_W)
        self.loss_ = float(beta * E_D + alpha * E_W)
        self.loss_history_ = np.array(history)  # columns: epoch, normalised MSE, γ, α, β
        return self

    def _cg_budget(self, epoch):
        """CG iterations allowed in this epoch's LM step: cg_miniter at epoch 1 rising linearly to
        cg_maxiter at cg_ramp_epochs (early steps are far from the optimum, rough solves do)."""
        lo = self.cg_maxiter if self.cg_miniter is None else min(self.cg_miniter, self.cg_maxiter)
        frac = min(1.0, (epoch - 1) / max(1, self.cg_ramp_epochs))
        return int(round(lo + frac * (self.cg_maxiter - lo)))

    # -- the matrix-free pieces: H v, the preconditioner, tr(H⁻¹) -------------------------------
    def _apply_H(self, w_p, x_p, cache_p, beta, shift):
        """v -> (2β JᵀJ + shift I) v, the Jacobian products in the product precision, result float64."""
        net, pdt = self.net_, x_p.dtype
        w_p = tuple(net.unpack(w_p))

        def apply(v):
            JtJv = net.vjp(w_p, x_p, cache_p, net.jvp(w_p, x_p, cache_p, v.to(pdt))).to(torch.float64)
            return 2 * beta * JtJv + shift * v
        return apply

    def _preconditioner(self, w_p, x_p, cache_p, epoch=1):
        """The data the preconditioner needs at this point: K-FAC factors, or diag(JᵀJ)."""
        if self.preconditioner == "kfac":
            return ("kfac", self.net_.kfac(w_p, x_p, cache_p))
        if epoch % 5 == 1 or getattr(self, "_jtj_diag", None) is None:  # need not be fresh every epoch
            self._jtj_diag = self.net_.jtj_diagonal(w_p, x_p, cache_p).to(torch.float64)
        return ("jacobi", self._jtj_diag)

    def _precond_solve(self, pre, beta, shift):
        """r -> M⁻¹ r for M ≈ 2β JᵀJ + shift I (float64 in and out)."""
        kind, data = pre
        if kind == "jacobi":
            return 2 * beta * data + shift
        pdt = data[0][0].dtype
        solve = self.net_.kfac_inverse(data, 2 * beta, shift)
        return lambda r: solve(r.to(pdt)).to(torch.float64)

    def _precond_trace(self, pre, beta, shift):
        """tr(M⁻¹), exactly (M's eigenvalues are known)."""
        kind, data = pre
        if kind == "jacobi":
            return float((1.0 / (2 * beta * data + shift)).sum())
        return float(sum((1.0 / (2 * beta * la.double()[:, None] * lb.double()[None, :] + shift)).sum()
                         for la, _, lb, _ in data))

    def _trace_inverse(self, w, x, cache, alpha, beta, gen, JtJ=None):
        """tr(H⁻¹), H = 2β JᵀJ + 2α I: exact with JᵀJ given, else Hutchinson + PCG.

        The estimate uses the preconditioner M as a control variate:
        ``tr(H⁻¹) = tr(M⁻¹) + E[zᵀ(H⁻¹ − M⁻¹)z]``, tr(M⁻¹) exact, so only the (smaller)
        difference carries Hutchinson noise.
        """
        net = self.net_
        N = net.n_weights
        if JtJ is not None:
            L = torch.linalg.cholesky(2 * beta * JtJ + 2 * alpha * torch.eye(N, dtype=JtJ.dtype))
            return float(torch.trace(torch.cholesky_inverse(L)))
        pdt = torch.float32 if self.product_dtype == "float32" else torch.float64
        w_p, x_p, cache_p = w.to(pdt), x.to(pdt), tuple(c.to(pdt) for c in cache)
        pre = self._preconditioner(w_p, x_p, cache_p)
        apply_H = self._apply_H(w_p, x_p, cache_p, beta, 2 * alpha)
        M = self._precond_solve(pre, beta, 2 * alpha)
        M_inv = M if callable(M) else (lambda r: r / M)
        # zᵀ H⁻¹ z from a truncated CG solve (CG's energy-norm optimality makes zᵀx_k converge fast).
        # The Rademacher probes are drawn once per fit and each solve starts at the previous
        # solution for the same probe: H changes little between re-estimates, so a few CG
        # iterations suffice, and γ does not jitter from fresh probe noise at every update.
        if getattr(self, "_probe_z", None) is None or len(self._probe_z) != self.probes \
                or self._probe_z[0].numel() != N:
            self._probe_z = [(torch.randint(0, 2, (N,), generator=gen) * 2 - 1).to(torch.float64)
                             for _ in range(self.probes)]
            self._probe_s = [None] * self.probes
        total = 0.0
        for i, z in enumerate(self._probe_z):
            s, its = _pcg(apply_H, z, M, x0=self._probe_s[i], tol=self.cg_tol,
                          maxiter=2 * self.cg_maxiter if self.trace_maxiter is None else self.trace_maxiter)
            self.cg_iterations_ = getattr(self, "cg_iterations_", 0) + its
            self._probe_s[i] = s
            total += float(z @ s) - float(z @ M_inv(z))
        return self._precond_trace(pre, beta, 2 * alpha) + total / self.probes

    # -- use --------------------------------------------------------------------------------
    def _check(self):
        if not hasattr(self, "weights_"):
            raise NotFittedError("ResidualNetwork is not fitted; call fit() first")

    def predict(self, q) -> np.ndarray:
        """Predicted residual Δz (n, 6) (m, rad) for joint coordinates q (n, 6) rad.

        For an ensemble (weights_ of shape (K, N_w), see :meth:`from_members`) the mean of the
        K members' predictions, each mapped back with its own target mapping.
        """
        self._check()
        x = torch.as_tensor(self.input_mapping_.apply(np.asarray(q, dtype=float).reshape(-1, 6)),
                            dtype=self.weights_.dtype)
        W = self.weights_ if self.weights_.ndim == 2 else self.weights_[None]
        mean = np.asarray(self.target_mapping_.mean, dtype=float).reshape(len(W), -1)
        scale = np.asarray(self.target_mapping_.scale, dtype=float).reshape(len(W), -1)
        out = 0.0
        with torch.no_grad(), _threads(getattr(self, "n_threads", None)):
            for w, mu, sd in zip(W, mean, scale):
                y, _ = self.net_.forward(w, x)
                out = out + (y.numpy().astype(float) * sd + mu)
        return out / len(W)

    @classmethod
    def from_members(cls, hidden, weights, input_mapping: Mapping, target_means, target_scales,
                     **attributes) -> "ResidualNetwork":
        """A fitted network from trained weights: one member (weights (N_w,), target mapping (6,))
        or an ensemble whose prediction is the members' mean (weights (K, N_w), mappings (K, 6)).
        attributes: fitted-state values to set (e.g. ``alpha_``, ``n_epochs_``)."""
        net = cls(hidden=tuple(int(h) for h in hidden))
        net.net_ = MLP(6, net.hidden, 6)
        w = torch.as_tensor(np.asarray(weights, dtype=float))
        if w.shape[-1] != net.net_.n_weights or w.ndim not in (1, 2):
            raise DataError(f"weights of shape {tuple(w.shape)} do not fit hidden sizes {net.hidden}")
        net.weights_ = w
        net.input_mapping_ = input_mapping
        net.target_mapping_ = Mapping(np.asarray(target_means, dtype=float), np.asarray(target_scales, dtype=float))
        net.alpha_ = net.beta_ = net.gamma_ = float("nan")
        net.n_epochs_ = 0
        for k, v in attributes.items():
            setattr(net, k, v)
        return net

    # -- safe persistence: tensors and plain values only, loaded with weights_only=True ---------
    def save(self, path) -> None:
        self._check()
        state = {
            # /1: one network; /2: an ensemble (weights (K, N_w), target mappings (K, 6))
            "format": "campaign.ResidualNetwork/2" if self.weights_.ndim == 2 else "campaign.ResidualNetwork/1",
            "hidden": torch.tensor(list(self.hidden), dtype=torch.int64),
            "weights": self.weights_.detach().clone(),
            "input_mean": torch.tensor(self.input_mapping_.mean), "input_scale": torch.tensor(self.input_mapping_.scale),
            "target_mean": torch.tensor(self.target_mapping_.mean),
            "target_scale": torch.tensor(self.target_mapping_.scale),
            "alpha": self.alpha_, "beta": self.beta_, "gamma": self.gamma_, "n_epochs": self.n_epochs_,
        }
        torch.save(state, str(path))

    @classmethod
    def load(cls, path) -> "ResidualNetwork":
        try:
            state = torch.load(str(path), weights_only=True)
        except Exception as exc:  # torch raises several types for a bad file
            raise DataError(f"{path}: not a saved residual network ({exc.__class__.__name__})") from None
        if not isinstance(state, dict) or state.get("format") not in ("campaign.ResidualNetwork/1",
                                                                     "campaign.ResidualNetwork/2"):
            raise DataError(f"{path}: not a saved residual network (unknown format)")
        hidden = tuple(int(v) for v in state["hidden"])
        net = cls(hidden=hidden)
        net.net_ = MLP(6, hidden, 6)
        net.weights_ = state["weights"]
        if net.weights_.shape[-1] != net.net_.n_weights or net.weights_.ndim != (2 if state["format"].endswith("/2") else 1):
            raise DataError(f"{path}: weights do not match hidden sizes {hidden}")
        net.input_mapping_ = Mapping(state["input_mean"].numpy(), state["input_scale"].numpy())
        net.target_mapping_ = Mapping(state["target_mean"].numpy(), state["target_scale"].numpy())
        net.alpha_, net.beta_, net.gamma_ = float(state["alpha"]), float(state["beta"]), float(state["gamma"])
        net.n_epochs_ = int(state["n_epochs"])
        return net
