import numpy as np
import pytest
import torch
from scipy.optimize import minimize

from campaign.ann import ResidualNetwork, br_update, compensate_pose
from campaign.ann.lm import MatrixFreeSolver, LMWorkspace, exact_trace_inverse, pcg
from campaign.ann.mlp import MLP
from campaign.errors import ConfigError, DataError, NotFittedError
from campaign.identify.ann_stage import parse_sizes
from campaign.model.kinematics import pose_error


@pytest.fixture
def small_net():
    torch.manual_seed(0)
    net = MLP(6, (7, 5), 6)
    g = torch.Generator().manual_seed(1)
    w = net.init(g, torch.float64) + 0.3 * torch.randn(net.n_weights, generator=g, dtype=torch.float64)
    x = torch.randn(13, 6, generator=g, dtype=torch.float64)
    return net, w, x, g


def test_structured_jvp_and_vjp_equal_torch_func(small_net):
    net, w, x, g = small_net
    f = lambda ww: net.forward(ww, x)[0]
    _, cache = net.forward(w, x)
    v = torch.randn(net.n_weights, generator=g, dtype=torch.float64)
    u = torch.randn(13, 6, generator=g, dtype=torch.float64)
    torch.testing.assert_close(net.jvp(w, x, cache, v), torch.func.jvp(f, (w,), (v,))[1], atol=1e-13, rtol=0)
    _, pullback = torch.func.vjp(f, w)
    torch.testing.assert_close(net.vjp(w, x, cache, u), pullback(u)[0], atol=1e-13, rtol=0)


def test_full_jacobian_and_its_gram_diagonal_equal_torch_func(small_net):
    net, w, x, _ = small_net
    J = torch.func.jacrev(lambda ww: net.forward(ww, x)[0])(w).reshape(13 * 6, -1)
    torch.testing.assert_close(net.jacobian(w, x), J, atol=1e-13, rtol=0)
    _, cache = net.forward(w, x)
    torch.testing.assert_close(net.jtj_diagonal(w, x, cache), torch.diag(J.T @ J), atol=1e-12, rtol=0)


def test_br_update_reaches_the_closed_form_evidence_maximum_of_a_linear_model():
    """For y = Φw the evidence has a closed form; MacKay's fixed point must maximise it."""
    rng = np.random.default_rng(0)
    n, N = 60, 8
    Phi = rng.normal(size=(n, N))
    t = Phi @ rng.normal(0, 0.7, N) + rng.normal(0, 0.3, n)

    def posterior(alpha, beta):
        H = 2 * beta * Phi.T @ Phi + 2 * alpha * np.eye(N)
        w = np.linalg.solve(H, 2 * beta * Phi.T @ t)
        e = Phi @ w - t
        return H, w, float(e @ e), float(w @ w)

    alpha, beta = 1.0, 1.0
    for _ in range(500):
        H, w, E_D, E_W = posterior(alpha, beta)
        gamma, alpha, beta = br_update(np.trace(np.linalg.inv(H)), N, n, alpha, E_D, E_W)

    def neg_log_evidence(log_ab):
        a, b = np.exp(log_ab)
        H, w, E_D, E_W = posterior(a, b)
        _, logdet = np.linalg.slogdet(H)
        return -(-b * E_D - a * E_W - 0.5 * logdet + 0.5 * N * np.log(2 * np.pi)
                 - 0.5 * N * np.log(np.pi / a) - 0.5 * n * np.log(np.pi / b))

    best = minimize(neg_log_evidence, x0=[0.0, 0.0], method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-12})
    a_ref, b_ref = np.exp(best.x)
    assert alpha == pytest.approx(a_ref, rel=1e-4)
    assert beta == pytest.approx(b_ref, rel=1e-4)
    lam = np.linalg.eigvalsh(2 * b_ref * Phi.T @ Phi)
    assert gamma == pytest.approx(np.sum(lam / (lam + 2 * a_ref)), rel=1e-4)


def smooth_data(n, seed=0):
    rng = np.random.default_rng(seed)
    lo, hi = -np.ones(6) * 2.5, np.ones(6) * 2.5
    q = rng.uniform(lo, hi, size=(n, 6))
    dz = np.stack([1e-4 * np.sin(q[:, 1]) * np.cos(q[:, 2]), 2e-4 * np.sin(q[:, 0] + q[:, 1]),
                   1e-4 * np.cos(2 * q[:, 2]), 1e-3 * np.sin(q[:, 3]), 5e-4 * np.cos(q[:, 4]),
                   1e-3 * np.sin(q[:, 1] - q[:, 2])], axis=1)
    return q, dz + rng.normal(0, 1e-6, dz.shape), lo, hi


def test_network_learns_a_smooth_residual():
    q, dz, lo, hi = smooth_data(600)
    net = ResidualNetwork(hidden=(16, 16), q_lower=lo, q_upper=hi, max_epochs=150, seed=0).fit(q[:500], dz[:500])
    res = dz[500:] - net.predict(q[500:])
    assert np.sqrt(np.mean(res ** 2)) < 0.2 * np.sqrt(np.mean(dz[500:] ** 2))
    assert 0 < net.gamma_ < net.net_.n_weights


def test_matrix_free_lm_step_equals_the_direct_solve(small_net):
    net, w, x, g = small_net
    _, cache = net.forward(w, x)
    alpha, beta, mu = 0.3, 2.0, 1e-2
    J = net.jacobian(w, x)
    A = 2 * beta * J.T @ J + (2 * alpha + mu) * torch.eye(net.n_weights, dtype=torch.float64)
    b = torch.randn(net.n_weights, generator=g, dtype=torch.float64)
    apply_A = lambda v: 2 * beta * net.vjp(w, x, cache, net.jvp(w, x, cache, v)) + (2 * alpha + mu) * v
    diag = 2 * beta * net.jtj_diagonal(w, x, cache) + 2 * alpha + mu
    step, _ = pcg(apply_A, b, diag, tol=1e-12, maxiter=2000)
    torch.testing.assert_close(step, torch.linalg.solve(A, b), atol=1e-8, rtol=1e-8)


def test_hutchinson_trace_of_the_inverse_hessian_matches_the_exact_trace(small_net):
    net, w, x, g = small_net
    _, cache = net.forward(w, x)
    alpha, beta = 0.5, 3.0
    J = net.jacobian(w, x)
    exact = exact_trace_inverse(J.T @ J, alpha, beta)
    solver = MatrixFreeSolver(probes=400, cg_maxiter=200)
    estimate = solver.trace_inverse(net, w, x, cache, alpha, beta, g, LMWorkspace())
    assert estimate == pytest.approx(exact, rel=0.05)


def test_training_is_reproducible_with_a_seed():
    q, dz, lo, hi = smooth_data(200)
    a = ResidualNetwork(hidden=(8, 8), q_lower=lo, q_upper=hi, max_epochs=30, seed=5).fit(q, dz)
    b = ResidualNetwork(hidden=(8, 8), q_lower=lo, q_upper=hi, max_epochs=30, seed=5).fit(q, dz)
    np.testing.assert_array_equal(a.predict(q), b.predict(q))


def test_saved_network_reloads_to_identical_outputs(tmp_path):
    q, dz, lo, hi = smooth_data(200)
    net = ResidualNetwork(hidden=(8, 4), q_lower=lo, q_upper=hi, max_epochs=20).fit(q, dz)
    net.save(tmp_path / "net.pt")
    again = ResidualNetwork.load(tmp_path / "net.pt")
    np.testing.assert_array_equal(again.predict(q), net.predict(q))


def test_loading_a_file_that_is_not_a_network_fails_cleanly(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"\x80\x04garbage")
    with pytest.raises(DataError, match="not a saved residual network"):
        ResidualNetwork.load(bad)


def test_input_mapping_uses_the_joint_limits():
    from campaign.ann import joint_mapping

    m = joint_mapping([-1.0, 0.0], [3.0, 2.0])
    u = np.random.default_rng(0).uniform([-1.0, 0.0], [3.0, 2.0], size=(200000, 2))
    np.testing.assert_allclose(m.apply(u).mean(axis=0), 0, atol=0.01)
    np.testing.assert_allclose(m.apply(u).var(axis=0), 1, atol=0.01)


def test_compensation_removes_a_known_residual(robot, rng):
    from campaign.model.kinematics import forward

    q = rng.uniform(robot.q_lower, robot.q_upper, size=(5, 6))
    T = forward(robot, q)
    dz = rng.normal(0, 1e-3, (5, 6))
    T_meas = compensate_pose(T, dz)
    np.testing.assert_allclose(pose_error(T, T_meas), dz, atol=1e-9)


def test_bad_inputs_are_named():
    with pytest.raises(NotFittedError):
        ResidualNetwork().predict(np.zeros((1, 6)))
    with pytest.raises(DataError, match="finite"):
        ResidualNetwork(max_epochs=1).fit(np.full((4, 6), np.nan), np.zeros((4, 6)))
    with pytest.raises(ConfigError, match="N1xN2"):
        parse_sizes("64-32")
    assert parse_sizes("16x16, 64x32") == ((16, 16), (64, 32))


def test_structured_gauss_newton_matrix_equals_jt_j(small_net):
    net, w, x, _ = small_net
    J = net.jacobian(w, x)
    _, cache = net.forward(w, x)
    torch.testing.assert_close(net.gauss_newton(w, x, cache, chunk=5), J.T @ J, atol=1e-12, rtol=0)


def test_kfac_preconditioner_inverts_its_kronecker_blocks_and_is_exact_on_the_output_layer(small_net):
    net, w, x, g = small_net
    _, cache = net.forward(w, x)
    factors = net.kfac(w, x, cache)

    def apply_K(v):  # (A ⊗ B) vec(V) = vec(A V Bᵀ) per layer block V = (W | b)
        parts, out = net.unpack(v), []
        for (la, Qa, lb, Qb), dW, db in zip(factors, parts[0::2], parts[1::2]):
            V = (Qa * la) @ Qa.T @ torch.cat([dW, db[:, None]], 1) @ (Qb * lb) @ Qb.T
            out += [V[:, :-1].reshape(-1), V[:, -1]]
        return torch.cat(out)

    v = torch.randn(net.n_weights, generator=g, dtype=torch.float64)
    scale, shift = 2.5, 0.7
    y = net.kfac_solve(factors, v, scale, shift)
    torch.testing.assert_close(scale * apply_K(y) + shift * y, v, atol=1e-10, rtol=1e-10)
    n_out_block = net.sizes[4] + net.sizes[5]
    u = torch.zeros(net.n_weights, dtype=torch.float64)
    u[-n_out_block:] = torch.randn(n_out_block, generator=g, dtype=torch.float64)
    JtJu = net.vjp(w, x, cache, net.jvp(w, x, cache, u))
    torch.testing.assert_close(apply_K(u)[-n_out_block:], JtJu[-n_out_block:], atol=1e-10, rtol=1e-10)


def test_full_jacobian_reference_and_matrix_free_training_agree_on_a_small_problem():
    """Same first LM step (CG solved tightly in float64), γ from Hutchinson close to the exact one,
    and the same early training curve (later the non-convex paths may part)."""
    q, dz, lo, hi = smooth_data(300)
    kw = dict(hidden=(8, 8), q_lower=lo, q_upper=hi, max_epochs=5, seed=1)
    full = ResidualNetwork(solver="full", **kw).fit(q, dz)
    cg = ResidualNetwork(solver="cg", cg_maxiter=500, probes=64, trace_maxiter=500, cg_tol=1e-10,
                         product_dtype="float64", **kw).fit(q, dz)
    assert cg.loss_history_[0, 1] == pytest.approx(full.loss_history_[0, 1], rel=1e-8)
    assert cg.gamma_ == pytest.approx(full.gamma_, rel=0.05)
    np.testing.assert_allclose(cg.loss_history_[:, 1], full.loss_history_[:, 1], rtol=0.02)
