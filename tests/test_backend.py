"""Factor-graph backends (SL(4) and Sim(3)) against exact ground truth."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest
from scipy.linalg import expm, logm
from scipy.spatial.transform import Rotation

from sl4slam.backend import Backend, BackendUpdateError, Sim3Backend, SL4Backend, SL4PoseGraph, SubmapBackend, make_backend
from sl4slam.config import BackendConfig
from sl4slam.errors import UserError

NUM_SUBMAPS = 21  # node 0 plus 20 odometry steps


# ---------------------------------------------------------------------------- helpers
def sl4_basis() -> np.ndarray:
    """(15, 4, 4) orthonormal basis of sl(4), in GTSAM's coordinate order (rotations, shears, diagonals)."""
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    basis = []
    for sign in (-1.0, 1.0):  # skew-symmetric, then symmetric off-diagonal
        for i, j in pairs:
            B = np.zeros((4, 4))
            B[i, j], B[j, i] = 1.0, sign
            basis.append(B / np.sqrt(2.0))
    for diagonal in ([1, -1, 0, 0], [1, 1, -2, 0], [1, 1, 1, -3]):
        d = np.array(diagonal, dtype=np.float64)
        basis.append(np.diag(d / np.linalg.norm(d)))
    return np.stack(basis)


SL4_BASIS = sl4_basis()


def sl4_coordinates(A: np.ndarray) -> np.ndarray:
    """Coordinates (15,) of a 4x4 matrix's traceless part in :data:`SL4_BASIS`."""
    return np.einsum("kij,ij->k", SL4_BASIS, A)


def sl4_exp(xi: np.ndarray) -> np.ndarray:
    return expm(np.einsum("k,kij->ij", xi, SL4_BASIS))


def sl4_log(H: np.ndarray) -> np.ndarray:
    return sl4_coordinates(np.real(logm(H)))


def random_sl4(rng: np.random.Generator, scale: float) -> np.ndarray:
    return sl4_exp(rng.normal(scale=scale, size=15))


def random_sim3(rng: np.random.Generator, rot: float, trans: float, log_scale: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.exp(rng.normal(scale=log_scale)) * Rotation.from_rotvec(rng.normal(scale=rot, size=3)).as_matrix()
    T[:3, 3] = rng.normal(scale=trans, size=3)
    return T


def chain(steps: list[np.ndarray]) -> list[np.ndarray]:
    """Ground-truth nodes ``H_world_k`` from relative steps ``H_{k-1}_k``."""
    nodes = [np.eye(4)]
    for step in steps:
        nodes.append(nodes[-1] @ step)
    return nodes


def run(backend: Backend, odometry: list[np.ndarray], loops: list[tuple[int, int, np.ndarray]]) -> dict[int, np.ndarray]:
    """Feed the chain one submap at a time; each loop is added together with its newest node."""
    backend.add_submap(0, None)
    backend.update()
    for k, H_prev_cur in enumerate(odometry, start=1):
        backend.add_submap(k, H_prev_cur)
        for i, j, H_i_j in loops:
            if max(i, j) == k:
                backend.add_loop(i, j, H_i_j)
        backend.update()
    return backend.world_estimate().H_world_submap


def map_error(estimates: dict[int, np.ndarray], truth: list[np.ndarray]) -> float:
    """Mean Frobenius distance between estimated and true nodes."""
    return float(np.mean([np.linalg.norm(estimates[k] - truth[k]) for k in range(len(truth))]))


def sl4_problem(seed: int, odometry_noise: float):
    rng = np.random.default_rng(seed)
    steps = [random_sl4(rng, 0.08) for _ in range(NUM_SUBMAPS - 1)]
    truth = chain(steps)
    odometry = [step @ random_sl4(rng, odometry_noise) for step in steps]
    return truth, odometry


# ---------------------------------------------------------------------------- residual convention
def test_sl4_factor_residual_is_the_papers():
    """GTSAM's error on our factor is -Log(H_world_i^-1 H_world_j H_i_j^-1), to second order."""
    rng = np.random.default_rng(0)
    backend = SL4Backend(BackendConfig(sigma=1.0))
    H_i_j = random_sl4(rng, 0.6)  # far from the identity, so the factor's orientation matters
    H_world_i = random_sl4(rng, 0.3)
    delta = rng.normal(size=15)
    delta *= 1e-3 / np.linalg.norm(delta)
    H_world_j = H_world_i @ sl4_exp(delta) @ H_i_j  # so that Log(E) = delta
    values = gtsam.Values()
    values.insert(backend.graph.key(3), gtsam.SL4(H_world_i))
    values.insert(backend.graph.key(7), gtsam.SL4(H_world_j))

    error = backend.graph.relative_factor(3, 7, H_i_j, gtsam.noiseModel.Unit.Create(15)).unwhitenedError(values)

    E = np.linalg.inv(H_world_i) @ H_world_j @ np.linalg.inv(H_i_j)
    paper_residual = sl4_log(E)
    np.testing.assert_allclose(paper_residual, delta, atol=1e-12)
    # GTSAM's SL4 chart is first order: exactly Vee(E^-1 - I) ...
    np.testing.assert_allclose(error, sl4_coordinates(np.linalg.inv(E) - np.eye(4)), atol=1e-12)
    # ... which is -Log(E) up to O(|delta|^2).
    assert np.linalg.norm(-error - paper_residual) < 2 * np.linalg.norm(delta) ** 2
    # The naive orientation (i, j, H_i_j) conjugates the residual by H_i_j: first-order different.
    naive = gtsam.BetweenFactorSL4(backend.graph.key(3), backend.graph.key(7), gtsam.SL4(H_i_j), gtsam.noiseModel.Unit.Create(15))
    assert np.linalg.norm(naive.unwhitenedError(values) - paper_residual) > 0.2 * np.linalg.norm(delta)


def test_sim3_factor_residual_is_the_papers_exactly():
    rng = np.random.default_rng(1)
    backend = Sim3Backend(BackendConfig(sigma=1.0))
    H_i_j = random_sim3(rng, 0.5, 2.0, 0.3)
    H_world_i = random_sim3(rng, 0.5, 2.0, 0.3)
    H_world_j = random_sim3(rng, 0.5, 2.0, 0.3)
    values = gtsam.Values()
    values.insert(backend.graph.key(0), backend.graph._to_gtsam(H_world_i))
    values.insert(backend.graph.key(1), backend.graph._to_gtsam(H_world_j))

    error = backend.graph.relative_factor(0, 1, H_i_j, gtsam.noiseModel.Unit.Create(7)).unwhitenedError(values)

    E = np.linalg.inv(H_world_i) @ H_world_j @ np.linalg.inv(H_i_j)
    # exp of the negated error in GTSAM's Sim(3) algebra must give back E (GTSAM's matrix of a
    # similarity is [R t/s; 0 1/s], the same projective map as [sR t; 0 1]).
    exp_residual = expm(gtsam.Similarity3.Hat(-error))
    np.testing.assert_allclose(exp_residual / exp_residual[3, 3], E, atol=1e-9)


def test_sim3_conversion_is_exact():
    rng = np.random.default_rng(2)
    T = random_sim3(rng, 1.0, 3.0, 0.5)
    backend = Sim3Backend(BackendConfig())
    S = backend.graph._to_gtsam(T)
    np.testing.assert_allclose(backend.graph._from_gtsam(S), T, atol=1e-13)
    point = rng.normal(size=3)
    np.testing.assert_allclose(S.transformFrom(point), T[:3, :3] @ point + T[:3, 3], atol=1e-13)


# ---------------------------------------------------------------------------- optimization
@pytest.mark.parametrize("kind", ["sl4", "sim3"])
def test_noise_free_measurements_are_reproduced(kind):
    rng = np.random.default_rng(3)
    if kind == "sl4":
        steps = [random_sl4(rng, 0.1) for _ in range(NUM_SUBMAPS - 1)]
    else:
        steps = [random_sim3(rng, 0.2, 0.5, 0.05) for _ in range(NUM_SUBMAPS - 1)]
    truth = chain(steps)
    loops = [(2, 20, np.linalg.inv(truth[2]) @ truth[20]), (15, 9, np.linalg.inv(truth[15]) @ truth[9])]
    estimates = run(make_backend(BackendConfig(kind=kind, graph="submap")), steps, loops)
    assert sorted(estimates) == list(range(NUM_SUBMAPS))
    for k, H in estimates.items():
        assert H.dtype == np.float64 and H.shape == (4, 4)
        np.testing.assert_allclose(H, truth[k], atol=1e-6)
        if kind == "sl4":
            assert np.linalg.det(H) == pytest.approx(1.0, abs=1e-9)
        else:
            np.testing.assert_array_equal(H[3], [0.0, 0.0, 0.0, 1.0])


def test_loop_closure_reduces_sl4_drift():
    truth, odometry = sl4_problem(seed=4, odometry_noise=0.02)
    loop = [(0, 20, np.linalg.inv(truth[0]) @ truth[20])]
    without = run(SL4Backend(BackendConfig()), odometry, [])
    backend = SL4Backend(BackendConfig())
    with_loop = run(backend, odometry, loop)
    error_without, error_with = map_error(without, truth), map_error(with_loop, truth)
    assert error_with < 0.6 * error_without
    # The loop was absorbed: the last node moved most of the way to the truth.
    assert np.linalg.norm(with_loop[20] - truth[20]) < 0.3 * np.linalg.norm(without[20] - truth[20])
    assert backend.num_loops == 1
    # ... and fully: batch Levenberg-Marquardt on the same graph from the odometry guess agrees.
    graph, initial = backend.graph.factor_graph(), gtsam.Values()
    for k, H in without.items():
        initial.insert(backend.graph.key(k), gtsam.SL4(H))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-15)
    params.setMaxIterations(200)
    batch = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    assert graph.error(backend.graph._isam.calculateBestEstimate()) == pytest.approx(graph.error(batch), rel=1e-4)
    for k in with_loop:
        np.testing.assert_allclose(with_loop[k], batch.atSL4(backend.graph.key(k)).matrix(), atol=1e-3)
    # the single-node read agrees with the full estimate
    for k in (0, 10, 20):
        np.testing.assert_allclose(backend.H_world_submap(k), with_loop[k], atol=1e-8)
    # the final polish removes what the relinearization threshold left
    final = backend.world_estimate(final=True).H_world_submap
    for k in with_loop:
        np.testing.assert_allclose(final[k], batch.atSL4(backend.graph.key(k)).matrix(), atol=1e-8)
    # ... without touching iSAM2: the graph keeps growing
    np.testing.assert_allclose(backend.world_estimate().H_world_submap[20], with_loop[20], atol=0)
    backend.add_submap(21, odometry[-1])
    backend.update()
    assert backend.num_submaps == 22


def test_sim3_loop_corrects_scale_drift():
    rng = np.random.default_rng(5)
    steps = [random_sim3(rng, 0.1, 1.0, 0.0) for _ in range(NUM_SUBMAPS - 1)]  # true scale 1 throughout
    truth = chain(steps)
    drift = np.diag([1.03, 1.03, 1.03, 1.0])  # every odometry step overestimates scale by 3 %
    odometry = [step @ drift for step in steps]
    loop = [(0, 20, np.linalg.inv(truth[0]) @ truth[20])]

    def scale(T):
        return float(np.cbrt(np.linalg.det(T[:3, :3])))

    without = run(Sim3Backend(BackendConfig()), odometry, [])
    with_loop = run(Sim3Backend(BackendConfig()), odometry, loop)
    assert scale(without[20]) == pytest.approx(1.03**20, rel=1e-9)
    assert abs(np.log(scale(with_loop[20]))) < 0.1 * abs(np.log(scale(without[20])))
    assert map_error(with_loop, truth) < 0.5 * map_error(without, truth)


def test_cauchy_kernel_resists_a_false_loop():
    truth, odometry = sl4_problem(seed=6, odometry_noise=0.005)
    rng = np.random.default_rng(7)
    false_loop = [(3, 17, random_sl4(rng, 0.5))]  # unrelated to the true H_3_17
    reference = run(SL4Backend(BackendConfig()), odometry, [])

    def displacement(kernel: str) -> float:
        estimates = run(SL4Backend(BackendConfig(loop_kernel=kernel)), odometry, false_loop)
        return float(np.mean([np.linalg.norm(estimates[k] - reference[k]) for k in reference]))

    moved_plain, moved_huber, moved_cauchy = displacement("none"), displacement("huber"), displacement("cauchy")
    assert moved_cauchy < 0.2 * moved_plain
    assert moved_huber < moved_plain


def test_loop_chi2_equals_the_batch_marginal_computation():
    """The loop gate's chi-square (from iSAM2's Bayes tree) against the textbook formula with a batch
    marginalization of the whole graph: e^T (A Sigma_ij A^T + Lambda^-1)^-1 e."""
    truth, odometry = sl4_problem(seed=4, odometry_noise=0.003)
    backend = SL4Backend(BackendConfig())  # (node 4 lies on the closed cycle 2..12: no revisit priors here)
    run(backend, odometry, [(2, 12, np.linalg.inv(truth[2]) @ truth[12])])
    rng = np.random.default_rng(5)
    measured = np.linalg.inv(truth[4]) @ truth[19] @ random_sl4(rng, 0.5)
    information = np.diag(rng.uniform(1e4, 1e5, backend.dim))
    chi2 = backend.loop_chi2(4, 19, measured, information)

    values = backend.graph._isam.calculateBestEstimate()
    factor = backend.graph.relative_factor(4, 19, measured, gtsam.noiseModel.Unit.Create(backend.dim))
    blocks = dict(zip(factor.keys(), np.split(factor.linearize(values).jacobian()[0], 2, axis=1)))
    keys = [backend.graph.key(19), backend.graph.key(4)]
    A = np.concatenate([blocks[k] for k in keys], axis=1)
    joint = gtsam.Marginals(backend.graph.factor_graph(), values).jointMarginalCovariance(keys).fullMatrix()
    error = np.asarray(factor.unwhitenedError(values))
    expected = error @ np.linalg.solve(A @ joint @ A.T + np.linalg.inv(information), error)
    # iSAM2's tree is linearized where its variables last moved by more than the relinearization threshold
    assert chi2 > 1 and chi2 == pytest.approx(expected, rel=1e-3)


# ---------------------------------------------------------------------------- revisits of closed places
def lap_problem(kind: str, laps: int, places: int = 10, seed: int = 3):
    """A camera going round the same ``places`` lap after lap: truth, noisy odometry, and a loop from
    every node of a later lap to the same place one lap earlier (``H_i_j`` exact)."""
    rng = np.random.default_rng(seed)
    draw = (lambda: random_sl4(rng, 0.08)) if kind == "sl4" else (lambda: random_sim3(rng, 0.1, 1.0, 0.05))
    place = [np.eye(4)] + [draw() for _ in range(places - 1)]
    truth = [place[k % places] for k in range(laps * places)]
    noise = (lambda: random_sl4(rng, 0.01)) if kind == "sl4" else (lambda: random_sim3(rng, 0.01, 0.05, 0.01))
    odometry = [np.linalg.inv(truth[k - 1]) @ truth[k] @ noise() for k in range(1, len(truth))]
    loops = [(k - places, k, np.linalg.inv(truth[k - places]) @ truth[k]) for k in range(places, len(truth))]
    return truth, odometry, loops


@pytest.mark.parametrize("kind", ["sl4", "sim3"])
def test_revisits_reach_isam2_as_priors_and_the_final_polish_exactly(kind):
    """Every loop after the first of a lap ties to a place on an already closed cycle: iSAM2 holds it
    as a prior on the newer node, the final polish as the loop itself, and lands on the same optimum
    as a graph that holds every loop exactly."""
    truth, odometry, loops = lap_problem(kind, laps=4)
    group = SL4Backend if kind == "sl4" else Sim3Backend
    exact, revisits = group(BackendConfig(kind=kind)), group(BackendConfig(kind=kind), revisit_priors=True)
    without_loops = run(group(BackendConfig(kind=kind)), odometry, [])
    online = run(revisits, odometry, loops)
    run(exact, odometry, loops)
    # one loop per lap closes a new stretch (node 0..10, 11..21, 22..32), the others revisit it
    assert revisits.num_loops == len(loops) == 30 and revisits.graph.num_revisit_priors == 27
    assert exact.graph.num_revisit_priors == 0

    def unary(graph):
        return sum(1 for k in range(graph.size()) if len(graph.at(k).keys()) == 1)

    assert unary(revisits.graph._isam.getFactorsUnsafe()) == 1 + 27 and unary(revisits.graph.factor_graph()) == 1
    assert revisits.graph.factor_graph().size() == exact.graph.factor_graph().size() == revisits.graph._isam.getFactorsUnsafe().size()
    # the priors already pull the newer laps onto the map while the run goes on ...
    assert map_error(online, truth) < 0.5 * map_error(without_loops, truth)
    # ... and the polished map is the exact graph's optimum
    polished, optimum = revisits.graph.final_estimates(), exact.graph.final_estimates()
    for k in optimum:
        np.testing.assert_allclose(polished[k], optimum[k], atol=1e-4)  # both stop at GN convergence
    graph = exact.graph.factor_graph()
    values = exact.graph._isam.calculateBestEstimate()
    for k, H in polished.items():
        values.update(exact.graph.key(k), exact.graph._to_gtsam(H))
    assert graph.error(values) == pytest.approx(graph.error(exact.graph.polished_values()), rel=1e-6)


def test_revisit_priors_keep_the_bayes_tree_from_growing_with_the_laps():
    """The cost of a loop update follows the Bayes tree's cliques: with every lap tied to the one
    before, their fill grows with the laps; with revisits held as priors it stays flat."""

    def fill_per_node(revisit_priors: bool, laps: int) -> float:
        truth, odometry, loops = lap_problem("sl4", laps=laps)
        backend = SL4Backend(BackendConfig(), revisit_priors=revisit_priors)
        run(backend, odometry, loops)
        return backend.graph._isam.treeNnz() / backend.num_submaps

    exact_growth = fill_per_node(False, 8) / fill_per_node(False, 3)
    revisit_growth = fill_per_node(True, 8) / fill_per_node(True, 3)
    assert exact_growth > 1.5 and revisit_growth < 1.15


def test_a_revisit_is_gated_as_the_prior_isam2_takes():
    """The loop gate's chi-square of a revisit: the prior's residual on the newer node against that
    node's marginal (batch marginalization of iSAM2's graph) plus the measurement's covariance."""
    truth, odometry = sl4_problem(seed=4, odometry_noise=0.003)
    backend = SL4Backend(BackendConfig(), revisit_priors=True)
    run(backend, odometry, [(2, 12, np.linalg.inv(truth[2]) @ truth[12])])
    rng = np.random.default_rng(5)
    measured = np.linalg.inv(truth[4]) @ truth[19] @ random_sl4(rng, 0.05)
    information = np.diag(rng.uniform(1e4, 1e5, backend.dim))
    assert backend.graph.is_revisit(4, 19) and not backend.graph.is_revisit(13, 19)
    chi2 = backend.loop_chi2(4, 19, measured, information)

    newer, prior, moved = backend.graph.revisit_prior(4, 19, measured, information)
    assert newer == 19
    np.testing.assert_allclose(prior, backend.H_world_submap(4) @ measured / np.linalg.det(measured) ** 0.25, atol=1e-9)
    values = backend.graph._isam.calculateBestEstimate()
    factor = gtsam.PriorFactorSL4(backend.graph.key(19), gtsam.SL4(prior), gtsam.noiseModel.Unit.Create(15))
    A = factor.linearize(values).jacobian()[0]
    marginal = gtsam.Marginals(backend.graph._isam.getFactorsUnsafe(), values).marginalCovariance(backend.graph.key(19))
    error = np.asarray(factor.unwhitenedError(values))
    expected = error @ np.linalg.solve(A @ marginal @ A.T + np.linalg.inv(moved), error)
    assert chi2 > 1 and chi2 == pytest.approx(expected, rel=1e-3)
    # the moved information describes the same noise: X_19 = X_4 H exp(-Ad(H^-1) xi) for X_19^-1 X_4 = H^-1 exp(xi)
    xi = 1e-4 * rng.normal(size=15)
    X4 = backend.H_world_submap(4)
    X19 = X4 @ np.linalg.inv(np.linalg.inv(measured) @ sl4_exp(xi))
    moved_xi = sl4_log(np.linalg.inv(prior) @ X19 * np.linalg.det(measured) ** 0.25 / np.linalg.det(X4) ** 0.25)
    assert moved_xi @ moved @ moved_xi == pytest.approx(xi @ information @ xi, rel=1e-3)


class FailingLoopGraph(SL4PoseGraph):
    """GTSAM fails on the next loop update (as an indeterminate system would)."""

    fail_next_loop = False
    fail_after_first_step = False  # fail once iSAM2 has taken the loop's first step (relinearized there)

    def _solve(self, factors, values, loop_keys):
        if loop_keys and self.fail_next_loop:
            self.fail_next_loop = False
            if self.fail_after_first_step:
                self._isam.update(factors, values)
                params = gtsam.ISAM2UpdateParams()
                params.force_relinearize = True
                self._isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), params)
            raise RuntimeError("\nIndeterminate linear system detected near variable s9 (simulated)")
        return super()._solve(factors, values, loop_keys)


def FailingLoopBackend(config: BackendConfig, revisit_priors: bool = False) -> SubmapBackend:
    return SubmapBackend(FailingLoopGraph(config, revisit_priors))


@pytest.mark.parametrize("after_first_step", [False, True])
def test_a_failed_loop_update_restores_the_estimate_it_started_from(after_first_step):
    """A graph that fails to absorb a loop is rebuilt at the estimate it had, not at the nodes' first
    guesses (which an earlier loop has left behind), and keeps growing: also when the failing loop
    had already moved iSAM2's linearization point."""
    truth, odometry = sl4_problem(seed=6, odometry_noise=0.03)
    backend = FailingLoopBackend(BackendConfig(), revisit_priors=True)
    backend.graph.fail_after_first_step = after_first_step
    before = run(backend, odometry, [(1, 20, np.linalg.inv(truth[1]) @ truth[20])])
    guesses = chain(odometry)
    assert max(np.abs(before[k] - guesses[k]).max() for k in before) > 0.05  # the loop moved the map
    optimum = backend.world_estimate(final=True).H_world_submap  # (iSAM2 itself stops iterating within loop_step_threshold of it)
    backend.graph.fail_next_loop = True
    wrong = np.linalg.inv(truth[3]) @ truth[17] @ random_sl4(np.random.default_rng(1), 0.1)  # a step to undo
    backend.add_loop(3, 17, wrong)
    with pytest.raises(BackendUpdateError, match="^RuntimeError: Indeterminate"):  # the message's first line
        backend.update()
    after = backend.world_estimate().H_world_submap
    assert backend.num_loops == 1 and sorted(after) == sorted(before)
    # the failed loop was a revisit (node 3 lies on the cycle 1..20): gone from both graphs
    assert backend.graph.num_revisit_priors == 0 and backend.graph.factor_graph().size() == backend.graph._isam.getFactorsUnsafe().size()
    # rebuilt at the optimum (within iSAM2's own step there, ~1e-4: SL(4)'s first-order chart);
    # rebuilt from the first guesses, one step left it 0.02 away
    assert max(np.abs(after[k] - optimum[k]).max() for k in before) < 1e-3
    backend.add_submap(NUM_SUBMAPS, odometry[0])
    backend.update()
    np.testing.assert_allclose(backend.H_world_submap(NUM_SUBMAPS), after[NUM_SUBMAPS - 1] @ odometry[0], atol=1e-6)


# ---------------------------------------------------------------------------- guards and bookkeeping
@pytest.mark.parametrize("kind", ["sl4", "sim3"])
def test_invalid_inputs_are_refused(kind):
    backend = make_backend(BackendConfig(kind=kind, graph="submap"))
    backend.add_submap(0, None)
    reflection = np.diag([-1.0, 1.0, 1.0, 1.0])  # det = -1: no SL(4) or Sim(3) representative
    not_finite = np.eye(4)
    not_finite[0, 3] = np.nan
    for bad in (reflection, not_finite, np.zeros((4, 4)), np.eye(3)):
        with pytest.raises(ValueError):
            backend.add_submap(1, bad)
    assert backend.num_submaps == 1
    backend.add_submap(1, np.eye(4))
    with pytest.raises(ValueError):
        backend.add_loop(0, 1, reflection)
    with pytest.raises(ValueError):
        backend.add_loop(0, 5, np.eye(4))  # unknown submap
    with pytest.raises(ValueError):
        backend.add_submap(1, np.eye(4))  # duplicate id
    with pytest.raises(ValueError):
        backend.add_submap(2, None)  # only the first submap takes None
    assert backend.num_loops == 0
    backend.update()
    np.testing.assert_allclose(backend.H_world_submap(1), np.eye(4), atol=1e-9)


def test_sim3_refuses_non_similarity():
    backend = Sim3Backend(BackendConfig())
    backend.add_submap(0, None)
    shear = np.eye(4)
    shear[0, 1] = 0.3
    projective = np.eye(4)
    projective[3, 0] = 0.1
    for bad in (shear, projective):
        with pytest.raises(ValueError):
            backend.add_submap(1, bad)


def test_sl4_scales_input_to_unit_determinant():
    backend = SL4Backend(BackendConfig())
    backend.add_submap(0, None)
    step = random_sl4(np.random.default_rng(8), 0.1)
    backend.add_submap(1, 3.0 * step)  # projectively the same map
    np.testing.assert_allclose(backend.H_world_submap(1), step, atol=1e-12)  # guess before update
    backend.update()
    np.testing.assert_allclose(backend.H_world_submap(1), step, atol=1e-9)


def test_pure_odometry_update_does_not_iterate():
    backend = SL4Backend(BackendConfig())
    _, odometry = sl4_problem(seed=9, odometry_noise=0.02)
    run(backend, odometry, [])
    assert backend.graph.last_update_iterations == 1
    assert backend.graph.num_updates == NUM_SUBMAPS


def test_make_backend_builds_the_named_graph_and_the_section_checks_itself():
    assert isinstance(make_backend(BackendConfig(kind="sim3", graph="submap")), Sim3Backend)
    assert isinstance(make_backend(BackendConfig(graph="submap")), SL4Backend)
    assert make_backend(BackendConfig(graph="keyframe")).design == "keyframe"
    for bad in (dict(kind="se3"), dict(loop_kernel="tukey"), dict(sigma=0.0), dict(loop_kernel_width=-1.0),
                dict(relinearize_skip=0)):
        with pytest.raises(UserError):
            dataclasses.replace(BackendConfig(), **bad).validate()


@pytest.mark.parametrize("kind", ["sl4", "sim3"])
def test_a_frozen_graph_reads_the_same_estimates_and_takes_nothing_more(kind):
    """``freeze`` drops iSAM2 at the end of a run: the estimate, polished or not, reads as before,
    and the graph refuses more factors and the loop test (which needs iSAM2)."""
    truth, odometry, loops = lap_problem(kind, laps=2)
    group = SL4Backend if kind == "sl4" else Sim3Backend
    backend = group(BackendConfig(kind=kind), revisit_priors=True)
    run(backend, odometry, loops)
    before, polished = backend.world_estimate().H_world_submap, backend.world_estimate(final=True).H_world_submap
    backend.add_submap(len(odometry) + 1, odometry[0])  # pending: nothing is dropped yet
    assert not backend.freeze() and backend.graph._isam is not None
    backend.update()
    before, polished = backend.world_estimate().H_world_submap, backend.world_estimate(final=True).H_world_submap
    assert backend.freeze() and backend.freeze()  # twice: nothing more to do
    assert backend.graph._isam is None and backend.graph._committed_factors.size() == 0
    after, polished_after = backend.world_estimate().H_world_submap, backend.world_estimate(final=True).H_world_submap
    assert before.keys() == after.keys() == polished_after.keys()
    for k in before:
        np.testing.assert_array_equal(after[k], before[k])  # the same values, kept
        np.testing.assert_array_equal(polished_after[k], polished[k])  # the same polish from them
    np.testing.assert_array_equal(backend.H_world_submap(3), before[3])
    with pytest.raises(RuntimeError, match="frozen"):
        backend.add_submap(len(odometry) + 2, odometry[0])
    with pytest.raises(RuntimeError, match="frozen"):
        backend.loop_chi2(0, 3, np.eye(4), np.eye(backend.graph.dim))
    assert backend.num_submaps == len(odometry) + 2  # the refused submap was not counted


def test_a_graph_lets_the_main_thread_recurse_as_deep_as_a_long_run_needs():
    """GTSAM walks iSAM2's Bayes tree recursively and a keyframe chain's tree is as deep as the
    chain: building a graph raises the soft stack limit (within the hard one, never lowering it)."""
    import resource

    from sl4slam.backend.pose_graph import GRAPH_STACK_BYTES, allow_deep_graphs

    soft, hard = resource.getrlimit(resource.RLIMIT_STACK)
    SL4PoseGraph(BackendConfig())
    now, _ = resource.getrlimit(resource.RLIMIT_STACK)
    expected = GRAPH_STACK_BYTES if hard == resource.RLIM_INFINITY else min(GRAPH_STACK_BYTES, hard)
    assert now == resource.RLIM_INFINITY or now >= max(expected, soft if soft != resource.RLIM_INFINITY else 0)
    assert allow_deep_graphs(1 << 20) == now  # a smaller limit never lowers it


@pytest.mark.slow
def test_the_joint_marginal_across_a_50000_node_chain_does_not_overflow_the_stack():
    """With the usual 8 MiB stack, iSAM2's joint marginal of the two ends of a 50,000-node SL(4)
    chain overflows it (a segmentation fault, as a 41,600-keyframe lap replay ended); the graph's
    raised limit lets it finish. In a subprocess, started with the usual limit; about 6 minutes on a
    core alone."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent('''
        import resource, gtsam
        from sl4slam.backend import SL4PoseGraph
        from sl4slam.config import BackendConfig
        graph = SL4PoseGraph(BackendConfig())
        isam = graph._isam
        noise = gtsam.noiseModel.Isotropic.Sigma(15, 0.1)
        graph_ = gtsam.NonlinearFactorGraph(); values = gtsam.Values()
        graph_.add(gtsam.PriorFactorSL4(graph.key(0), gtsam.SL4(), noise)); values.insert(graph.key(0), gtsam.SL4())
        isam.update(graph_, values)
        for i in range(1, 50000):
            graph_ = gtsam.NonlinearFactorGraph(); values = gtsam.Values()
            graph_.add(gtsam.BetweenFactorSL4(graph.key(i - 1), graph.key(i), gtsam.SL4(), noise))
            values.insert(graph.key(i), gtsam.SL4())
            isam.update(graph_, values)
        isam.jointMarginalCovariance([graph.key(0), graph.key(49999)])
        print("ok")
    ''')
    run = subprocess.run(["bash", "-c", f"ulimit -S -s 8192 && {sys.executable} -c \"$0\"", script],
                         capture_output=True, text=True, timeout=1800)
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr[-2000:]
