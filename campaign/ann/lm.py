"""Bayesian-regularised Levenberg-Marquardt (MacKay 1992; Foresee & Hagan 1997): the training
loop and its two solver strategies.

The loop (:func:`train_lm`) minimises ``F = β E_D + α E_W`` with LM steps on the Gauss-Newton
Hessian ``H = 2β JᵀJ + 2α I`` and re-estimates ``γ = N_w − 2α tr(H⁻¹)``, ``α = γ / (2 E_W)``,
``β = (N_d − γ) / (2 E_D)`` (:func:`br_update`) every ``gamma_every`` epochs, the first time after
``gamma_every`` epochs at a weak prior (:func:`initial_hyperparameters`). How each LM system is
solved and how tr(H⁻¹) is obtained is the strategy's:

* :class:`MatrixFreeSolver` (``solver="cg"``, the default): J is never formed; conjugate
  gradients on the structured products ``J v`` / ``Jᵀ u`` (:class:`~campaign.ann.mlp.MLP`) in
  float32, preconditioned by the block-diagonal Kronecker (K-FAC) approximation of JᵀJ (exact
  damped inverse by eigendecomposition of the small factors) or by diag(JᵀJ); tr(H⁻¹) by a
  Hutchinson estimate with the preconditioner's exact trace as control variate
  (:meth:`MatrixFreeSolver.trace_inverse`).
* :class:`FullSolver` (``solver="full"``, the reference): JᵀJ assembled exactly in float64
  (:meth:`MLP.gauss_newton`), Cholesky solves, the exact trace (:func:`exact_trace_inverse`).

Strategies hold only their settings; what changes during a training (Hutchinson probes and
their last solutions, a cached diagonal, the Gram matrix carried from a re-estimate to the next
step, CG iteration counts) lives in an :class:`LMWorkspace` made per training, never on the
estimator. Derivations and measurements: docs/ann.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

_DTYPES = {"float32": torch.float32, "float64": torch.float64}


@dataclass
class LMWorkspace:
    """Scratch state of one training (one per :func:`train_lm` call).

    probe_z, probe_s: the Hutchinson probes (drawn once per training) and each probe's last
    solution H⁻¹z (the next estimate starts there); jtj_diag: diag(JᵀJ) of the Jacobi
    preconditioner (refreshed every 5 epochs); jtj_next: the full solver's JᵀJ computed at a
    re-estimate, reused by the next epoch's step; cg_iterations: CG iterations so far (steps and
    probes).
    """

    probe_z: list | None = None
    probe_s: list | None = None
    jtj_diag: torch.Tensor | None = None
    jtj_next: torch.Tensor | None = None
    cg_iterations: int = 0


#: the prior's share of the objective at the start, ``α₀ E_W = INITIAL_PRIOR_SHARE · β₀ E_D``: weak,
#: so that the first ``gamma_every`` epochs fit the data before MacKay's re-estimate judges the fit.
#: MATLAB trainbr's start (γ = N_w, α₀ = N_w / 2E_W, β₀ = (N_d − N_w) / 2E_D, re-estimated after the
#: first step) puts α₀/β₀ at 10-40 whatever the data; with N_d ≈ N_w (120 poses, a (16, 16) net:
#: 720 residuals, 486 weights) that prior outweighs the data, the weights shrink to the w = 0
#: saddle of every tanh net (all hidden-layer Jacobian columns vanish there), γ → 0, α → ∞, and
#: no LM step leaves it ("mu_max" after 5 epochs, γ = 1-5): docs/ann.md, "Small campaigns"
INITIAL_PRIOR_SHARE = 1e-3


def initial_hyperparameters(E_D, E_W, n_data):
    """(α₀, β₀) of a training: β₀ = N_d / (2 E_D) (the noise no larger than the initial misfit),
    α₀ with α₀ E_W = INITIAL_PRIOR_SHARE · β₀ E_D (a weak prior)."""
    beta = n_data / (2 * max(E_D, 1e-12))
    alpha = INITIAL_PRIOR_SHARE * beta * max(E_D, 1e-12) / max(E_W, 1e-12)
    return alpha, beta


def br_update(gamma_trace_inv, n_weights, n_data, alpha, E_D, E_W):
    """One MacKay / Foresee-Hagan update: returns (gamma, alpha, beta).

    gamma_trace_inv: tr(H⁻¹) with H = 2β JᵀJ + 2α I at the current point.
    """
    gamma = n_weights - 2.0 * alpha * gamma_trace_inv
    # γ ≤ N_d − 1 too: a network with more weights than residuals could otherwise reach γ ≥ N_d, and
    # β = (N_d − γ) / 2E_D would turn zero or negative (the weights then grow without bound)
    gamma = float(min(max(gamma, 1e-6), n_weights, max(n_data - 1.0, 1e-6)))
    alpha = gamma / (2.0 * max(E_W, 1e-300))
    beta = (n_data - gamma) / (2.0 * max(E_D, 1e-300))
    return gamma, alpha, beta


def pcg(apply_A, b, precond, x0=None, tol=1e-3, maxiter=50):
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


def exact_trace_inverse(JtJ, alpha, beta) -> float:
    """tr(H⁻¹) for H = 2β JᵀJ + 2α I, from the Cholesky inverse (the reference)."""
    N = JtJ.shape[0]
    L = torch.linalg.cholesky(2 * beta * JtJ + 2 * alpha * torch.eye(N, dtype=JtJ.dtype, device=JtJ.device))
    return float(torch.trace(torch.cholesky_inverse(L)))


def hessian_product(net, w_p, x_p, cache_p, beta, shift):
    """v -> (2β JᵀJ + shift I) v: the Jacobian products in the precision of w_p, x_p, the result
    float64."""
    pdt = x_p.dtype
    w_p = tuple(net.unpack(w_p))

    def apply(v):
        JtJv = net.vjp(w_p, x_p, cache_p, net.jvp(w_p, x_p, cache_p, v.to(pdt))).to(torch.float64)
        return 2 * beta * JtJv + shift * v
    return apply


def preconditioner_solve(net, pre, beta, shift):
    """r -> M⁻¹ r for M ≈ 2β JᵀJ + shift I (float64 in and out); pre = ("kfac", factors of
    :meth:`MLP.kfac`) or ("jacobi", diag(JᵀJ)). For Jacobi the diagonal of M itself (a tensor,
    as :func:`pcg` takes it)."""
    kind, data = pre
    if kind == "jacobi":
        return 2 * beta * data + shift
    pdt = data[0][0].dtype
    solve = net.kfac_inverse(data, 2 * beta, shift)
    return lambda r: solve(r.to(pdt)).to(torch.float64)


def preconditioner_trace(pre, beta, shift) -> float:
    """tr(M⁻¹), exactly (M's eigenvalues are known)."""
    kind, data = pre
    if kind == "jacobi":
        return float((1.0 / (2 * beta * data + shift)).sum())
    return float(sum((1.0 / (2 * beta * la.double()[:, None] * lb.double()[None, :] + shift)).sum()
                     for la, _, lb, _ in data))


class FullSolver:
    """The reference strategy: exact JᵀJ (float64, :meth:`MLP.gauss_newton`), Cholesky solves,
    exact tr(H⁻¹)."""

    name = "full"

    def linearise(self, net, w, x, cache, epoch, ws: LMWorkspace):
        """This epoch's system: JᵀJ at w (the one of the last re-estimate when it was made here)."""
        JtJ = ws.jtj_next if ws.jtj_next is not None else net.gauss_newton(w, x, cache)
        ws.jtj_next = None
        return JtJ

    def solve(self, JtJ, grad, beta, shift, epoch, x0, ws: LMWorkspace):
        """The LM step ``−(2β JᵀJ + shift I)⁻¹ grad``, or None when the matrix is not positive
        definite in floating point (the loop then raises μ)."""
        eye = torch.eye(JtJ.shape[0], dtype=JtJ.dtype, device=JtJ.device)
        L, info = torch.linalg.cholesky_ex(2 * beta * JtJ + shift * eye)
        if int(info) != 0:
            return None
        return -torch.cholesky_solve(grad[:, None], L)[:, 0]

    def trace_inverse(self, net, w, x, cache, alpha, beta, gen, ws: LMWorkspace) -> float:
        """Exact tr(H⁻¹) at w; JᵀJ is kept in the workspace for the next step."""
        ws.jtj_next = net.gauss_newton(w, x, cache)
        return exact_trace_inverse(ws.jtj_next, alpha, beta)


@dataclass(frozen=True)
class MatrixFreeSolver:
    """The matrix-free strategy: PCG on structured products, K-FAC or Jacobi preconditioner,
    Hutchinson trace. Settings as :class:`~campaign.ann.network.ResidualNetwork`'s of the same
    names (``warm_start`` is its ``cg_warm_start``)."""

    preconditioner: str = "kfac"
    product_dtype: str = "float32"
    cg_maxiter: int = 20
    cg_miniter: int | None = None
    cg_ramp_epochs: int = 100
    cg_tol: float = 1e-3
    probes: int = 4
    trace_maxiter: int | None = 20
    warm_start: bool = False

    name = "cg"

    def cg_budget(self, epoch) -> int:
        """CG iterations allowed in this epoch's LM step: cg_miniter at epoch 1 rising linearly to
        cg_maxiter at cg_ramp_epochs (early steps are far from the optimum, rough solves do)."""
        lo = self.cg_maxiter if self.cg_miniter is None else min(self.cg_miniter, self.cg_maxiter)
        frac = min(1.0, (epoch - 1) / max(1, self.cg_ramp_epochs))
        return int(round(lo + frac * (self.cg_maxiter - lo)))

    def _at(self, w, x, cache):
        pdt = _DTYPES[self.product_dtype]
        return w.to(pdt), x.to(pdt), tuple(c.to(pdt) for c in cache)

    def _preconditioner(self, net, w_p, x_p, cache_p, epoch, ws: LMWorkspace):
        if self.preconditioner == "kfac":
            return ("kfac", net.kfac(w_p, x_p, cache_p))
        if epoch % 5 == 1 or ws.jtj_diag is None:  # need not be fresh every epoch
            ws.jtj_diag = net.jtj_diagonal(w_p, x_p, cache_p).to(torch.float64)
        return ("jacobi", ws.jtj_diag)

    def linearise(self, net, w, x, cache, epoch, ws: LMWorkspace):
        """This epoch's system: the point in the product precision and its preconditioner data."""
        w_p, x_p, cache_p = self._at(w, x, cache)
        return net, w_p, x_p, cache_p, self._preconditioner(net, w_p, x_p, cache_p, epoch, ws)

    def solve(self, system, grad, beta, shift, epoch, x0, ws: LMWorkspace):
        """The LM step from a truncated PCG solve of ``(2β JᵀJ + shift I) δ = −grad``."""
        net, w_p, x_p, cache_p, pre = system
        step, its = pcg(hessian_product(net, w_p, x_p, cache_p, beta, shift), -grad,
                        preconditioner_solve(net, pre, beta, shift), x0=x0 if self.warm_start else None,
                        tol=self.cg_tol, maxiter=self.cg_budget(epoch))
        ws.cg_iterations += its
        return step

    def trace_inverse(self, net, w, x, cache, alpha, beta, gen, ws: LMWorkspace) -> float:
        """tr(H⁻¹), H = 2β JᵀJ + 2α I, by Hutchinson + PCG with the preconditioner M as a control
        variate: ``tr(H⁻¹) = tr(M⁻¹) + E[zᵀ(H⁻¹ − M⁻¹)z]``, tr(M⁻¹) exact, so only the (smaller)
        difference carries Hutchinson noise.

        The Rademacher probes are drawn (from gen) once per workspace and each solve starts at
        the previous solution for the same probe: H changes little between re-estimates, so a
        few CG iterations suffice, and γ does not jitter from fresh probe noise at every update.
        """
        N = net.n_weights
        w_p, x_p, cache_p = self._at(w, x, cache)
        pre = self._preconditioner(net, w_p, x_p, cache_p, 1, ws)
        apply_H = hessian_product(net, w_p, x_p, cache_p, beta, 2 * alpha)
        M = preconditioner_solve(net, pre, beta, 2 * alpha)
        M_inv = M if callable(M) else (lambda r: r / M)
        if ws.probe_z is None or len(ws.probe_z) != self.probes or ws.probe_z[0].numel() != N:
            ws.probe_z = [(torch.randint(0, 2, (N,), generator=gen) * 2 - 1).to(torch.float64).to(w.device)
                          for _ in range(self.probes)]
            ws.probe_s = [None] * self.probes
        total = 0.0
        for i, z in enumerate(ws.probe_z):
            s, its = pcg(apply_H, z, M, x0=ws.probe_s[i], tol=self.cg_tol,
                         maxiter=2 * self.cg_maxiter if self.trace_maxiter is None else self.trace_maxiter)
            ws.cg_iterations += its
            ws.probe_s[i] = s
            total += float(z @ s) - float(z @ M_inv(z))
        return preconditioner_trace(pre, beta, 2 * alpha) + total / self.probes


@dataclass(frozen=True)
class LMOptions:
    """The loop's settings (as :class:`~campaign.ann.network.ResidualNetwork`'s of the same names)."""

    max_epochs: int = 2048
    gamma_every: int = 20
    min_rel_improvement: float = 1e-5
    patience: int = 15
    window: int = 50
    window_rtol: float = 1e-2
    mu_max: float = 1e10


@dataclass(frozen=True)
class LMResult:
    """What a training found: weights (N_w,) float64, the final α, β, γ, epochs run, why it stopped
    ("plateau", "converged", "mu_max", "max_epochs"), E_D and E_W, ``history`` (epochs, 5)
    (columns: epoch, normalised MSE, γ, α, β) and the CG iterations used (0 for the full solver)."""

    weights: torch.Tensor
    alpha: float
    beta: float
    gamma: float
    n_epochs: int
    stop_reason: str
    E_D: float
    E_W: float
    n_data: int
    history: np.ndarray
    cg_iterations: int

    @property
    def mse_normalised(self) -> float:
        return self.E_D / self.n_data

    @property
    def loss(self) -> float:
        return float(self.beta * self.E_D + self.alpha * self.E_W)


def train_lm(net, w, x, t, solver, gen, *, options: LMOptions = LMOptions(), progress=None,
             progress_every: int = 10) -> LMResult:
    """Train ``net`` (a :class:`~campaign.ann.mlp.MLP`) from weights w (N_w,) float64 on mapped
    inputs x (n, N_in) and targets t (n, N_out), float64, with BR-LM and the given strategy
    (:class:`MatrixFreeSolver` or :class:`FullSolver`). gen: the generator of the Hutchinson
    probes. progress: optional callable(epoch=, max_epochs=, mse=, gamma=) every
    ``progress_every`` epochs (and after the first).

    Stop rules: *plateau* (the normalised training MSE fell by less than ``window_rtol`` over the
    last ``window`` epochs and γ moved by less than 10 × that), *converged* (F fell by less than
    ``min_rel_improvement`` for ``patience`` epochs in a row), *mu_max* (no step lowers F even at
    μ = mu_max), or ``max_epochs``.
    """
    o = options
    ws = LMWorkspace()
    N = net.n_weights
    n_data = t.numel()
    y, cache = net.forward(w, x)
    e = y - t
    E_D, E_W = float((e * e).sum()), float((w * w).sum())
    # a weak prior first (INITIAL_PRIOR_SHARE: MATLAB trainbr's start collapses small data sets);
    # γ = N_w until the first re-estimate
    gamma = float(N)
    alpha, beta = initial_hyperparameters(E_D, E_W, n_data)
    mu = 5e-3
    history = []
    stall = 0
    delta = None
    epoch = 0
    stop = "max_epochs"
    for epoch in range(1, o.max_epochs + 1):
        F = beta * E_D + alpha * E_W
        grad = 2 * beta * net.vjp(w, x, cache, e) + 2 * alpha * w
        system = solver.linearise(net, w, x, cache, epoch, ws)
        accepted = False
        while mu <= o.mu_max:
            step = solver.solve(system, grad, beta, 2 * alpha + mu, epoch, delta, ws)
            if step is None:
                mu *= 10
                continue
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
        if epoch % o.gamma_every == 0:  # MacKay's update holds near the minimum of F, not at the start
            tr_inv = solver.trace_inverse(net, w, x, cache, alpha, beta, gen, ws)
            gamma, alpha, beta = br_update(tr_inv, N, n_data, alpha, E_D, E_W)
        history.append((epoch, E_D / n_data, gamma, alpha, beta))
        if progress is not None and (epoch % progress_every == 0 or epoch == 1):
            progress(epoch=epoch, max_epochs=o.max_epochs, mse=E_D / n_data, gamma=gamma)
        stall = stall + 1 if rel < o.min_rel_improvement else 0
        if stall >= o.patience:
            stop = "converged"
            break
        if o.window and epoch > o.window:
            _, mse_then, gamma_then, _, _ = history[-1 - o.window]
            mse_now = E_D / n_data
            if (mse_then - mse_now) < o.window_rtol * mse_now and \
                    abs(gamma - gamma_then) < 10 * o.window_rtol * gamma:
                stop = "plateau"
                break
    if not history or epoch < o.gamma_every:  # stopped before any re-estimate: one now, so γ, α, β are estimates
        tr_inv = solver.trace_inverse(net, w, x, cache, alpha, beta, gen, ws)
        gamma, alpha, beta = br_update(tr_inv, N, n_data, alpha, E_D, E_W)
    return LMResult(w, float(alpha), float(beta), float(gamma), epoch, stop, float(E_D), float(E_W), int(n_data),
                    np.array(history), ws.cg_iterations)
