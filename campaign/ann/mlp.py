"""The residual network as a flat parameter vector, with its structured Jacobian products.

An N_in - N1 - N2 - N_out multilayer perceptron (two tanh hidden layers, linear outputs) whose
weights are one flat vector ``w = (W1, b1, W2, b2, W3, b3)``. For such a net the products ``J v``
and ``Jᵀ u`` with the Jacobian of all outputs on all samples are a few matrix products with the
forward activations (no J formed); so are diag(JᵀJ), the Kronecker factors of its layer blocks
(K-FAC) and JᵀJ itself. The solver strategies (campaign.ann.lm), the batched Adam
(campaign.ann.adam) and the estimator (campaign.ann.network) all use this one description.
Also here: the affine input / target mappings and a context manager for torch's threads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch


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


def joint_limits(q_lower, q_upper, n_joints: int) -> tuple:
    """The input mapping's joint limits (q_lower (N,), q_upper (N,)), checked: N finite values
    each with q_upper > q_lower. None: the embedded default robot's (eq. 17), for 6 joints only;
    any other robot must give its own. ConfigError otherwise."""
    from campaign.errors import ConfigError

    if q_lower is None or q_upper is None:
        from campaign.model.robot import RobotModel

        robot = RobotModel.load()
        if robot.n_joints != n_joints:
            raise ConfigError(f"the network's inputs are {n_joints} joint values per pose: give q_lower and "
                              f"q_upper (the robot's joint limits) for a robot other than {robot.name}")
        q_lower = robot.q_lower if q_lower is None else q_lower
        q_upper = robot.q_upper if q_upper is None else q_upper
    lo, hi = np.asarray(q_lower, dtype=float), np.asarray(q_upper, dtype=float)
    if lo.shape != (n_joints,) or hi.shape != (n_joints,) or not np.all(np.isfinite(lo) & np.isfinite(hi)) \
            or not np.all(hi > lo):
        raise ConfigError(f"joint limits must be {n_joints} finite values each (one per joint of q) with "
                          f"q_upper > q_lower, got {lo}, {hi}")
    return lo, hi


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
                          torch.full((self.n_out,), float(n), dtype=x.dtype, device=x.device)])

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
        one = torch.ones((n, 1), dtype=x.dtype, device=x.device)
        pairs = []
        for A, inp in ((A1, x), (A2, h1), (None, h2)):
            xt = torch.cat([inp, one], 1)
            lb, Qb = torch.linalg.eigh((xt.T @ xt).double())
            if A is None:  # output layer: Σ_k e_k e_kᵀ / n · n = I, exact
                la = torch.ones(self.n_out, dtype=torch.float64, device=x.device)
                Qa = torch.eye(self.n_out, dtype=torch.float64, device=x.device)
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
        n, dt, dev = x.shape[0], x.dtype, x.device
        rows = [self.n1, self.n2, self.n_out]
        cols = [self.n_in + 1, self.n1 + 1, self.n2 + 1]
        # flat index of each (i, j) of the layer matrix (W | b): W row-major, then b
        perm, off = [], 0
        for r, c in zip(rows, cols):
            i = torch.arange(r, device=dev)[:, None]
            j = torch.arange(c, device=dev)[None, :]
            perm.append((off + torch.where(j < c - 1, i * (c - 1) + j, r * (c - 1) + i)).reshape(-1))
            off += r * c
        G = torch.zeros((self.n_weights, self.n_weights), dtype=dt, device=dev)
        for s0 in range(0, n, chunk):
            sl = slice(s0, min(n, s0 + chunk))
            m = sl.stop - sl.start
            one = torch.ones((m, 1), dtype=dt, device=dev)
            g_a2 = W3[None, :, :] * (1 - h2[sl] * h2[sl])[:, None, :]
            g_a1 = (g_a2 @ W2) * (1 - h1[sl] * h1[sl])[:, None, :]
            a = [g_a1, g_a2, torch.eye(self.n_out, dtype=dt, device=dev).expand(m, -1, -1)]
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
        rows = torch.empty((n, self.n_out, self.n_weights), dtype=x.dtype, device=x.device)
        for k in range(self.n_out):
            # per-sample gradients of output k: outer products per layer
            W1, b1, W2, b2, W3, b3 = self.unpack(w)
            h1, h2 = cache
            g_a2 = W3[k][None, :] * (1 - h2 * h2)
            g_a1 = (g_a2 @ W2) * (1 - h1 * h1)
            e = torch.zeros((n, self.n_out), dtype=x.dtype, device=x.device)
            e[:, k] = 1.0
            rows[:, k, :] = torch.cat([
                (g_a1[:, :, None] * x[:, None, :]).reshape(n, -1), g_a1,
                (g_a2[:, :, None] * h1[:, None, :]).reshape(n, -1), g_a2,
                (e[:, :, None] * h2[:, None, :]).reshape(n, -1), e], dim=1)
        return rows.reshape(n * self.n_out, self.n_weights)


class torch_threads:
    """Context manager: torch intra-op threads set to n (None: unchanged), restored on exit."""

    def __init__(self, n):
        self.n = n

    def __enter__(self):
        self.before = torch.get_num_threads()
        if self.n is not None:
            torch.set_num_threads(int(self.n))

    def __exit__(self, *exc):
        torch.set_num_threads(self.before)
