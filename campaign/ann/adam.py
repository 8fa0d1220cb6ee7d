"""Adam with early stopping, many networks of one size trained as one batched computation.

The members of a batch share the input poses q but each has its own fitting rows, validation
rows (for early stopping) and targets: the folds of a cross-validation, the two prior models,
or both. Their weights are stacked on a leading member axis and every layer is one batched
matrix product (``torch.baddbmm``), so B networks cost one network's Python overhead and the
flops run in large, efficient products. Adam is elementwise and the loss is the sum of the
members' own mean squared errors, so each member's trajectory is exactly the one it would have
alone (up to floating-point summation order). A member stops when its validation MSE has not
improved for ``patience`` epochs; it keeps its best weights and is dropped from the batch.

The network is the same as :class:`campaign.ann.mlp.MLP` (N - N1 - N2 - N_out, tanh, flat
weight vector in the same order), so a member's best weights load into a
:class:`~campaign.ann.network.ResidualNetwork` unchanged.

Device: everything runs on ``device`` (a GPU when given one); inputs come from and results go
back to numpy on the CPU, the mini-batch orders are drawn on the CPU (seeded generators), so
the same seeds give the same batches on every device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from campaign.ann.mlp import MLP


@dataclass(frozen=True)
class AdamOptions:
    """Hyperparameters of :func:`train_batched` (defaults from benchmarks/bench_ann.py --adam-rules).

    lr: Adam step size; batch: samples per mini-batch and member (None: n_fit / 16 clipped to
    [32, 256], so small data sets still take a dozen steps per epoch); max_epochs: bound; patience:
    epochs without a better validation MSE before a member stops; val_share: share of a
    member's training rows held out for early stopping; eval_every: epochs between
    validation checks; lr_decay_after: after this many epochs without improvement the step size
    of that member is halved once (a plateau schedule), 0 for none.
    """

    lr: float = 3e-3
    batch: int | None = None
    max_epochs: int = 2000
    patience: int = 60
    val_share: float = 0.15
    eval_every: int = 2
    lr_decay_after: int = 30
    lr_factor: float = 0.3
    max_cuts: int = 4
    dtype: str = "float32"


def _init(net: MLP, seeds, dtype) -> torch.Tensor:
    """Initial weight vectors (B, N_w), member b's from MLP.init seeded with seeds[b]."""
    return torch.stack([net.init(torch.Generator().manual_seed(int(s)), torch.float64) for s in seeds]).to(dtype)


def _unpack(net: MLP, P):
    B = P.shape[0]
    i, parts = 0, []
    for s, n in zip(net.shapes, net.sizes):
        parts.append(P[:, i:i + n].reshape(B, *s))
        i += n
    return parts


def _forward(net: MLP, P, x, cache=False):
    """Outputs (B, m, n_out) for stacked weights P (B, N_w) and inputs x (B, m, n_in)
    (with cache: also the hidden activations, for :func:`_mse_grad`)."""
    W1, b1, W2, b2, W3, b3 = _unpack(net, P)
    h1 = torch.tanh(torch.baddbmm(b1[:, None, :], x, W1.transpose(1, 2)))
    h2 = torch.tanh(torch.baddbmm(b2[:, None, :], h1, W2.transpose(1, 2)))
    out = torch.baddbmm(b3[:, None, :], h2, W3.transpose(1, 2))
    return (out, (h1, h2)) if cache else out


def _mse_grad(net: MLP, P, x, y):
    """Gradient (B, N_w) of Σ_b mean((out_b − y_b)²) by the chain rule written out (a dozen batched
    products; autograd's bookkeeping cost more than the small products themselves)."""
    W1, b1, W2, b2, W3, b3 = _unpack(net, P)
    out, (h1, h2) = _forward(net, P, x, cache=True)
    B, m, k = out.shape
    g3 = (out - y).mul_(2.0 / (m * k))
    a2 = torch.bmm(g3, W3).mul_(1 - h2 * h2)
    a1 = torch.bmm(a2, W2).mul_(1 - h1 * h1)
    return torch.cat([torch.bmm(a1.transpose(1, 2), x).reshape(B, -1), a1.sum(1),
                      torch.bmm(a2.transpose(1, 2), h1).reshape(B, -1), a2.sum(1),
                      torch.bmm(g3.transpose(1, 2), h2).reshape(B, -1), g3.sum(1)], dim=1)


def train_batched(hidden, x, targets, fit_rows, val_rows, *, seeds, options: AdamOptions = AdamOptions(),
                  device="cpu", progress=None):
    """Train B networks of one hidden size; returns (weights (B, N_w) float64 numpy, info per member).

    x: (n, N) mapped inputs (float); targets: (B, n, N_out) mapped targets per member (rows a member
    does not use may hold anything); fit_rows, val_rows: B integer index arrays into the n rows.
    progress: optional callable(epochs_done_now: int, active_members: int) called after every
    evaluation with the epochs run since the last call (for a whole-grid progress bar).
    info per member: ``epochs`` (run), ``best_epoch``, ``val_mse`` (normalised, at the best epoch).
    """
    dt = torch.float32 if options.dtype == "float32" else torch.float64
    dev = torch.device(device)
    net = MLP(x.shape[1], tuple(hidden), targets.shape[2])
    B = len(fit_rows)
    X = torch.as_tensor(np.asarray(x), dtype=dt, device=dev)
    Y = torch.as_tensor(np.asarray(targets), dtype=dt, device=dev)
    fit = [torch.as_tensor(np.asarray(r), dtype=torch.long, device=dev) for r in fit_rows]
    val = [torch.as_tensor(np.asarray(r), dtype=torch.long, device=dev) for r in val_rows]
    n_fit = max(len(r) for r in fit)
    bs = options.batch or int(min(256, max(32, n_fit // 16)))
    bs = min(bs, n_fit)
    steps = max(1, math.ceil(n_fit / bs))
    gens = [torch.Generator(device="cpu").manual_seed(int(s) + 7919) for s in seeds]

    P = _init(net, seeds, dt).to(dev)
    m, v = torch.zeros_like(P), torch.zeros_like(P)
    lr = torch.full((B, 1), options.lr, dtype=dt, device=dev)
    b1, b2, eps = 0.9, 0.999, 1e-8
    t = 0
    best_P = P.clone()
    best = np.full(B, np.inf)
    best_epoch = np.zeros(B, int)
    n_cuts = np.zeros(B, int)
    last_cut = np.zeros(B, int)
    epochs = np.zeros(B, int)
    active = np.arange(B)  # member ids still training, in the order of P's rows
    # validation rows padded to a rectangle (repeating a member's first row), masked in the mean
    n_val = max(len(r) for r in val)
    Vidx = torch.stack([torch.cat([r, r[:1].expand(n_val - len(r))]) for r in val])
    Vmask = torch.stack([torch.arange(n_val, device=dev) < len(r) for r in val]).to(dt)
    last_report = 0
    for epoch in range(1, options.max_epochs + 1):
        A = len(active)
        # each active member's permutation of its own fitting rows, wrapped to n_fit
        order = torch.stack([fit[a][torch.randperm(len(fit[a]), generator=gens[a]).to(dev)
                                    .repeat(math.ceil(n_fit / len(fit[a])))[:n_fit]] for a in active])
        Ya = Y[torch.as_tensor(active, device=dev)]
        ar = torch.arange(A, device=dev)[:, None]
        for s in range(steps):
            idx = order[:, s * bs:(s + 1) * bs]
            xb, yb = X[idx], Ya[ar, idx]
            g = _mse_grad(net, P, xb, yb)
            t += 1
            m.mul_(b1).add_(g, alpha=1 - b1)
            v.mul_(b2).addcmul_(g, g, value=1 - b2)
            # torch.optim.Adam's update: p -= lr / (1 - b1^t) · m / (sqrt(v / (1 - b2^t)) + eps)
            P.addcdiv_(m * (lr / (1 - b1 ** t)), (v.sqrt() / math.sqrt(1 - b2 ** t)).add_(eps), value=-1.0)
        epochs[active] = epoch
        if epoch % options.eval_every and epoch != options.max_epochs:
            continue
        with torch.no_grad():
            aidx = torch.as_tensor(active, device=dev)
            vi = Vidx[aidx]
            err = (_forward(net, P, X[vi]) - Y[aidx[:, None], vi]) ** 2
            vm = Vmask[aidx]
            val_mse = ((err.mean(2) * vm).sum(1) / vm.sum(1)).double().cpu().numpy()
        better = val_mse < best[active]
        if better.any():
            rows = np.flatnonzero(better)
            best_P[torch.as_tensor(active[rows], device=dev)] = P[torch.as_tensor(rows, device=dev)]
            best[active[rows]] = val_mse[rows]
            best_epoch[active[rows]] = epoch
        since = epoch - best_epoch[active]
        if options.lr_decay_after:
            # plateau schedule: the step size falls by lr_factor after lr_decay_after epochs
            # without improvement (counted from the best epoch or the last decrease)
            cut = (epoch - np.maximum(best_epoch[active], last_cut[active]) >= options.lr_decay_after) \
                & (n_cuts[active] < options.max_cuts)
            if cut.any():
                lr[torch.as_tensor(np.flatnonzero(cut), device=dev)] *= options.lr_factor
                n_cuts[active[cut]] += 1
                last_cut[active[cut]] = epoch
        keep = (since < options.patience) | ((epoch - last_cut[active] < options.patience) & (n_cuts[active] < options.max_cuts))
        if progress is not None:
            progress(epoch - last_report, int(A))
            last_report = epoch
        if not keep.all():
            if not keep.any():
                break
            k = torch.as_tensor(np.flatnonzero(keep), device=dev)
            P, m, v, lr = P[k].contiguous(), m[k].contiguous(), v[k].contiguous(), lr[k]
            active = active[keep]
    info = [{"epochs": int(epochs[b]), "best_epoch": int(best_epoch[b]), "val_mse": float(best[b])}
            for b in range(B)]
    return best_P.double().cpu().numpy(), info
