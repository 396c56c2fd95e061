"""The iSAM2 pose-graph engine on SL(4) or Sim(3) that both graph designs run on.

The engine is a chain of nodes as the paper's graph (section 4.4): a prior on the first node, a
between factor from each node to the one before it (odometry), a between factor per loop closure,
and a weak prior on the first node of every map segment. The submap graph makes each submap a node
(``H_world_submap``); the keyframe graph each keyframe. A relative
measurement ``H_i_j`` reads ``x_i ~ H_i_j x_j``, so a consistent map satisfies
``H_world_j = H_world_i H_i_j`` and the paper's residual is

    r_ij = Log(H_world_i^-1 H_world_j H_i_j^-1).

GTSAM's ``BetweenFactor(key_a, key_b, Z)`` evaluates ``Local(Z, X_a^-1 X_b)``, i.e. it places the
measurement on the *left* of the predicted relative transform: ``Local(Z, Y) = chart(Z^-1 Y)``.
Handing it ``(key_i, key_j, H_i_j)`` would give ``chart(H_i_j^-1 H_world_i^-1 H_world_j)``, which
equals the paper's residual only after a conjugation by ``H_i_j`` (its adjoint), so it would weight
directions differently for any measurement far from the identity. We therefore add the factor in
the reverse direction with the inverse measurement, ``(key_j, key_i, H_j_i = H_i_j^-1)``; its error
is ``chart(H_i_j H_world_j^-1 H_world_i) = chart(E^-1)`` with ``E = H_world_i^-1 H_world_j H_i_j^-1``
the paper's error element. Since ``Log(E^-1) = -Log(E)``, that is the paper's residual up to sign
(exactly for Sim(3), whose chart is ``Log``; to second order in the residual for SL(4), whose chart
in GTSAM is the first-order ``Vee(E^-1 - I)``). The tests check this numerically.

Noise. Each factor takes an information matrix in the tangent coordinates of its measurement
(``Z exp(xi)``, GTSAM's convention); ``None`` means the isotropic ``BackendConfig.sigma``.
``sl4slam.backend.evidence`` derives it from the alignment's own inliers.

The graph is optimized with iSAM2: a pure odometry step only eliminates the newest clique, so its
cost does not grow with the map. A loop factor makes iSAM2 re-eliminate the path from the loop's
older node to the root, and relinearize every variable whose step exceeds the threshold; both
follow the loop's span. Two thresholds keep that work small (``BackendConfig``): variables are
relinearized once their step exceeds ``relinearize_threshold`` (1e-2), and after a loop iSAM2
iterates only while some step exceeds ``loop_step_threshold`` (5e-2), i.e. when the loop
corrects real drift. The check for variables to relinearize reads every node, so it runs at
every ``relinearize_skip``-th update and at each of those loop iterations, not at every odometry
step. (One O(map) walk per update remains inside GTSAM: the temporary tree of a re-elimination
visits the whole tree below it when it is freed: about 0.7 ms per update at 5000 nodes.) The
estimate then sits within about 1e-4 (relative) of the optimal graph error;
:meth:`PoseGraph.final_estimates` removes that once, at the end of a run, with a batch
Gauss-Newton polish of the whole graph. (GTSAM's SL(4)
chart is first-order, so near the optimum the graph error is flat to about 1e-5 relative and
solutions differ by ~1e-4 in their entries: beyond that, "converged" has no meaning.)

Revisits. A map that goes round the same places lap after lap, each lap tied to the others by
loops, is a grid: its Bayes tree cliques widen with every lap, and so does the cost of each loop
update (decision: docs/decisions/isam2.md). So iSAM2 takes a loop as a between factor only when its older node is not yet
on a cycle that an earlier loop closed; a loop to a place that is (a revisit) reaches iSAM2 as a
prior on the newer node at the older node's current estimate (the keyframe graph's
``BackendConfig.revisit_priors``; the submap graph, a few hundred nodes where the keyframe graph
has thousands, does without it).
iSAM2's graph then stays a chain with one loop per closed stretch and unary factors, whatever the
laps. Every loop is kept exactly in :meth:`PoseGraph.factor_graph`, which the final
polish optimizes, so the map a run ends with is the exact graph's optimum.
"""

from __future__ import annotations

import bisect
import time
from abc import ABC, abstractmethod
from typing import Any, Sequence

import gtsam
import numpy as np

from .settings import BackendConfig
from .interface import BackendUpdateError

def check_matrix(name: str, M: Any) -> np.ndarray:
    """``M`` as a finite (4, 4) float64 array, else ``ValueError``."""
    M = np.asarray(M, dtype=np.float64)
    if M.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 matrix, got shape {M.shape}")
    if not np.all(np.isfinite(M)):
        raise ValueError(f"{name} contains NaN or Inf")
    return M


def adjoint_matrix(A: np.ndarray, generators: np.ndarray) -> np.ndarray:
    """``(dim, dim)`` matrix of ``xi -> vee(A hat(xi) A^-1)`` in the tangent basis ``generators``
    ``(dim, 4, 4)`` (any basis of the group's Lie algebra: SL(4)'s or Sim(3)'s)."""
    A = np.asarray(A, dtype=np.float64)
    conjugated = np.einsum("ij,mjk,kl->mil", A, generators, np.linalg.inv(A))  # A G_m A^-1
    basis = generators.reshape(len(generators), 16).T
    coefficients, *_ = np.linalg.lstsq(basis, conjugated.reshape(len(generators), 16).T, rcond=None)
    return coefficients


def transport_information(information: np.ndarray, A: np.ndarray, generators: np.ndarray) -> np.ndarray:
    """Information of a tangent noise ``xi`` re-expressed for ``Ad(A) xi``: ``Ad^-T I Ad^-1``.

    A between factor holds ``Z = H^-1`` with noise ``Z exp(xi)`` (module doc); for ``A H B`` that
    is ``B^-1 Z A^-1 exp(Ad(A) xi)``, so the keyframe graph moves a measurement's information this
    way when it moves the measurement onto keyframe nodes.
    """
    Ad_inv = np.linalg.inv(adjoint_matrix(A, generators))
    moved = Ad_inv.T @ np.asarray(information, dtype=np.float64) @ Ad_inv
    return 0.5 * (moved + moved.T)


class ClosedSpans:
    """Union of closed integer intervals ``[lo, hi]`` (positions in a graph's insertion order)."""

    def __init__(self) -> None:
        self.starts: list[int] = []
        self.ends: list[int] = []

    def add(self, lo: int, hi: int) -> None:
        """Add ``[lo, hi]``, merged with the intervals it overlaps or touches."""
        lo, hi = min(lo, hi), max(lo, hi)
        first = bisect.bisect_left(self.ends, lo - 1)  # the first interval ending at or after lo - 1
        last = bisect.bisect_right(self.starts, hi + 1)  # past the last one starting by hi + 1
        if first < last:
            lo, hi = min(lo, self.starts[first]), max(hi, self.ends[last - 1])
        self.starts[first:last], self.ends[first:last] = [lo], [hi]

    def contains(self, position: int) -> bool:
        k = bisect.bisect_right(self.starts, position) - 1
        return k >= 0 and position <= self.ends[k]


GRAPH_STACK_BYTES = 1 << 30
"""The stack a thread that works on a graph may grow to. GTSAM walks iSAM2's Bayes tree recursively,
and a keyframe chain's tree is about as deep as the chain: a lap replay of 41,600 keyframe nodes
overflowed the usual 8 MiB and ended in a segmentation fault. Only the pages used are taken."""


def allow_deep_graphs(limit: int = GRAPH_STACK_BYTES) -> int:
    """Raise the process's soft stack limit to ``limit`` bytes (never above the hard limit, never
    lower), so that the main thread's stack can grow as deep as GTSAM's recursion into a long
    run's graph goes (other threads keep the stack they were started with). Returns the soft limit
    now in force (0 where there are no resource limits)."""
    try:
        import resource
    except ImportError:  # no resource limits on this platform
        return 0
    soft, hard = resource.getrlimit(resource.RLIMIT_STACK)
    if soft == resource.RLIM_INFINITY or soft >= limit:
        return soft
    wanted = limit if hard == resource.RLIM_INFINITY else min(limit, hard)
    if wanted > soft:
        try:
            resource.setrlimit(resource.RLIMIT_STACK, (wanted, hard))
        except (ValueError, OSError):
            return soft
        return wanted
    return soft


def gauss_newton(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, max_iterations: int = 20) -> gtsam.Values:
    """``values`` moved to the optimum of ``graph`` by batch Gauss-Newton, one step at a time, each
    kept only while it lowers the error (GTSAM's SL(4) chart is first-order, so plain Gauss-Newton
    can overshoot at the 1e-7 level once converged); a singular step ends it. O(graph)."""
    error = graph.error(values)
    optimizer = gtsam.GaussNewtonOptimizer(graph, values)
    for _ in range(int(max_iterations)):
        try:
            optimizer.iterate()
        except RuntimeError:
            break
        new_error = optimizer.error()
        if not new_error < error:
            break
        converged = error - new_error <= 1e-12 * error
        values, error = gtsam.Values(optimizer.values()), new_error  # a copy: the optimizer owns its values
        if converged:
            break
    return values


POLISH_PEAK_PER_FACTOR_BYTE = 3.2
"""Peak memory of a Gauss-Newton polish over the bytes of its square-root information matrix
(COLAMD, as GTSAM orders it; every conditional's rows by all its columns): 2.1-3.0 measured on the
lap replay's graphs of 300-3000 submaps, rounded up (decision: docs/decisions/polish-memory.md)."""


def polish_peak_bytes(factor_keys: Sequence[Sequence[int]], dim: int) -> int:
    """Estimated peak memory of batch Gauss-Newton on a graph, from its structure alone.

    A symbolic elimination (COLAMD, the ordering GTSAM's optimizers use) gives the size of the
    square-root information matrix; the peak is :data:`POLISH_PEAK_PER_FACTOR_BYTE` times its bytes.

    Args:
        factor_keys: the keys of every factor (one or two each; a node held fixed is a variable too,
            with a unary constraint, which adds no fill).
        dim: the tangent dimension of every variable (15 for SL(4), 7 for Sim(3)).

    Returns:
        bytes; 0 for an empty graph.
    """
    graph = gtsam.SymbolicFactorGraph()
    for keys in factor_keys:
        graph.push_factor(*keys)
    if not graph.size():
        return 0
    tree = graph.eliminateMultifrontal(gtsam.Ordering.ColamdSymbolicFactorGraph(graph))
    entries, cliques = 0, list(tree.roots())
    while cliques:  # an explicit walk: a long run's tree is deeper than Python's recursion limit
        clique = cliques.pop()
        conditional = clique.conditional()
        frontals = conditional.nrFrontals()
        entries += frontals * (len(conditional.keys()) + 1) * dim * dim  # rows x (frontal + separator + rhs) columns
        cliques.extend(clique[i] for i in range(clique.nrChildren()))
    return int(POLISH_PEAK_PER_FACTOR_BYTE * 8 * entries)


def dense_polish_bytes(num_nodes: int, dim: int) -> int:
    """An upper bound on :func:`polish_peak_bytes` of any graph of ``num_nodes`` nodes: its factor
    dense (every node tied to every other), without a symbolic elimination."""
    return int(POLISH_PEAK_PER_FACTOR_BYTE * 8 * (num_nodes * dim) * (num_nodes * dim + 1) // 2)


def polish_blocks(newest: np.ndarray, factor_keys: Sequence[Sequence[int]], num_nodes: int, dim: int,
                  budget_bytes: int) -> list[tuple[int, int]]:
    """Split the nodes (in insertion order) into consecutive blocks whose polish fits a memory budget.

    A block ``[a, b)`` is polished with the factors whose newest node lies in it, the older nodes
    they reach held fixed; each block is the longest whose :func:`polish_peak_bytes` is within
    ``budget_bytes`` (at least one node), found by bisection.

    Args:
        newest: ``(F,)`` int the insertion rank of each factor's newest node, ascending.
        factor_keys: the keys of each factor, in the same order.
        num_nodes: how many nodes the graph has.
        dim: the tangent dimension of a node.
        budget_bytes: the memory a block's polish may take (positive).

    Returns:
        ``[(a, b), ...]`` covering ``0 .. num_nodes``; ``[(0, num_nodes)]`` when the whole graph fits.
    """
    def peak(a: int, b: int) -> int:
        lo, hi = np.searchsorted(newest, [a, b])
        return polish_peak_bytes(factor_keys[lo:hi], dim)

    if peak(0, num_nodes) <= budget_bytes:
        return [(0, num_nodes)]
    blocks, a = [], 0
    while a < num_nodes:
        lo, hi = a + 1, num_nodes  # the longest block [a, b) within the budget: lo fits (or must)
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if peak(a, mid) <= budget_bytes:
                lo = mid
            else:
                hi = mid - 1
        blocks.append((a, lo))
        a = lo
    return blocks


class PoseGraph(ABC):
    """Incremental (iSAM2) pose graph over nodes numbered by the caller; subclasses fix the group
    (SL(4) or Sim(3)). Nodes form a chain in the order they are added (:meth:`add_node` links a
    node to the one before it); loops join any two; every map segment starts with a prior.

    Attributes:
        kind: the group ("sl4" or "sim3"); dim: its tangent dimension (15 or 7).
        last_update_seconds: wall time of the most recent :meth:`update`.

    Args:
        config: sigmas, the loop kernel and iSAM2's thresholds (``BackendConfig``).
        revisit_priors: hold revisits of closed places as priors in iSAM2 (:meth:`is_revisit`); the
            keyframe graph turns it on with ``BackendConfig.revisit_priors``.
    """

    kind: str = ""
    dim: int = 0

    def __init__(self, config: BackendConfig, revisit_priors: bool = False) -> None:
        self.config = config
        self.revisit_priors = revisit_priors
        allow_deep_graphs()  # GTSAM's recursion into a long run's Bayes tree (GRAPH_STACK_BYTES)
        self._isam = self._new_isam()
        self._frozen: gtsam.Values | None = None  # iSAM2's last estimate, once freeze() dropped iSAM2
        self._prior_noise = gtsam.noiseModel.Isotropic.Sigma(self.dim, config.prior_sigma)
        self._segment_noise = gtsam.noiseModel.Isotropic.Sigma(self.dim, config.segment_sigma)

        self._order: list[int] = []  # node ids in insertion order
        self._known: set[int] = set()
        self._rank: dict[int, int] = {}  # node id -> position in insertion order
        self._segments: list[int] = []  # first node of every segment
        self._pending_factors = gtsam.NonlinearFactorGraph()
        self._pending_values = gtsam.Values()
        self._pending_loops = 0
        self._pending_ids: list[int] = []
        # Everything iSAM2 holds, with the initial guesses, so a failed update can be undone.
        self._committed_factors = gtsam.NonlinearFactorGraph()
        self._committed_values = gtsam.Values()
        # The graph as measured, with every loop between its two nodes: iSAM2 holds revisits of
        # closed places as priors instead (see add_loop); the final polish optimizes this one.
        self._pending_exact = gtsam.NonlinearFactorGraph()
        self._exact_factors = gtsam.NonlinearFactorGraph()
        self._closed = ClosedSpans()  # insertion-order spans of the cycles exact loops closed
        self._pending_spans: list[tuple[int, int]] = []
        self._pending_revisits = 0
        self._pending_loop_keys: list[int] = []  # GTSAM keys of the pending loop factors
        self.num_revisit_priors = 0
        self.polish_block_count = 1  # blocks the last polish took (polished_values)
        self._last_estimate: np.ndarray | None = None  # of the newest node, seeds the next guess

        self.num_loops = 0
        self.num_updates = 0
        self.last_update_seconds = 0.0
        self.total_update_seconds = 0.0
        self.last_update_iterations = 0

    def _new_isam(self) -> gtsam.ISAM2:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.config.relinearize_threshold)
        params.relinearizeSkip = self.config.relinearize_skip
        gauss_newton_params = gtsam.ISAM2GaussNewtonParams()
        gauss_newton_params.setWildfireThreshold(self.config.wildfire_threshold)
        params.setOptimizationParams(gauss_newton_params)
        return gtsam.ISAM2(params)

    # ------------------------------------------------------------------ group hooks
    @abstractmethod
    def _check(self, name: str, M: np.ndarray) -> np.ndarray:
        """Validate a (4, 4) input of this group and return its canonical float64 form."""

    @abstractmethod
    def _to_gtsam(self, M: np.ndarray) -> Any:
        """Canonical (4, 4) matrix -> GTSAM group element."""

    @abstractmethod
    def _from_gtsam(self, element: Any) -> np.ndarray:
        """GTSAM group element -> canonical (4, 4) float64 matrix."""

    @abstractmethod
    def _at(self, values: gtsam.Values, key: int) -> Any:
        """Typed read of one element from ``gtsam.Values``."""

    @abstractmethod
    def _between_factor(self, key_a: int, key_b: int, Z_a_b: Any, noise: Any) -> Any:
        """GTSAM between factor with error ``Local(Z_a_b, X_a^-1 X_b)``."""

    @abstractmethod
    def _prior_factor(self, key: int, Z: Any, noise: Any) -> Any:
        """GTSAM prior factor."""

    @abstractmethod
    def _equality_factor(self, key: int, value: Any) -> Any:
        """GTSAM factor that holds a variable at ``value`` (a hard constraint)."""

    def _estimate_one(self, key: int) -> Any:
        """iSAM2's current estimate of one variable (no full back-substitution); after
        :meth:`freeze`, the one it had then."""
        return self._at(self._frozen, key) if self._frozen is not None else self._isam_estimate_one(key)

    @abstractmethod
    def _isam_estimate_one(self, key: int) -> Any:
        """iSAM2's current estimate of one variable, read from iSAM2."""

    @abstractmethod
    def _hat(self, xi: np.ndarray) -> np.ndarray:
        """Tangent vector ``(dim,)`` -> Lie algebra element ``(4, 4)`` (GTSAM's ``Hat``)."""

    def _inverse(self, M: np.ndarray) -> np.ndarray:
        return np.linalg.inv(M)

    def generators(self) -> np.ndarray:
        return np.stack([self._hat(row) for row in np.eye(self.dim)])

    # ------------------------------------------------------------------ graph building
    @staticmethod
    def key(node: int) -> int:
        """GTSAM key of a node."""
        return gtsam.symbol("s", int(node))

    def noise_model(self, information: np.ndarray | None, loop: bool = False) -> Any:
        """GTSAM noise of a measurement: Gaussian with this information (None: isotropic ``sigma``),
        wrapped in the loop kernel for loops."""
        if information is None:
            base = gtsam.noiseModel.Isotropic.Sigma(self.dim, self.config.sigma)
        else:
            information = np.asarray(information, dtype=np.float64)
            if information.shape != (self.dim, self.dim) or not np.isfinite(information).all():
                raise ValueError(f"information must be a finite {self.dim}x{self.dim} matrix")
            base = gtsam.noiseModel.Gaussian.Information(0.5 * (information + information.T))
        kernel = self.config.loop_kernel
        if not loop or kernel == "none":
            return base
        estimators = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy}
        return gtsam.noiseModel.Robust.Create(estimators[kernel].Create(self.config.loop_kernel_width), base)

    def relative_factor(self, i: int, j: int, H_i_j: np.ndarray, noise: Any) -> Any:
        """Factor with residual (up to sign) ``Log(H_world_i^-1 H_world_j H_i_j^-1)``; see module doc."""
        H_j_i = self._inverse(H_i_j)
        return self._between_factor(self.key(j), self.key(i), self._to_gtsam(H_j_i), noise)

    def _check_id(self, node: int) -> int:
        if isinstance(node, bool) or not isinstance(node, (int, np.integer)) or node < 0:
            raise ValueError(f"node id must be a non-negative integer, got {node!r}")
        return int(node)

    def _check_new(self, node: int) -> int:
        node = self._check_id(node)
        if node in self._known:
            raise ValueError(f"node {node} was already added")
        return node

    def _push(self, factor: Any, exact: Any = None) -> None:
        """Queue a factor for iSAM2 and its exact form (``None``: the same) for the final polish."""
        self._live()
        self._pending_factors.push_back(factor)
        self._pending_exact.push_back(factor if exact is None else exact)

    def _insert(self, node: int, guess: np.ndarray, factor: Any) -> None:
        self._push(factor)
        self._pending_values.insert(self.key(node), self._to_gtsam(guess))
        self._rank[node] = len(self._order)
        self._order.append(node)
        self._known.add(node)
        self._pending_ids.append(node)
        self._last_estimate = guess

    def add_node(self, node: int, H_prev_node: np.ndarray | None, information: np.ndarray | None = None) -> None:
        """Add ``node``, linked to the previously added node by a between factor.

        Args:
            node: new, non-negative id.
            H_prev_node: (4, 4) map from this node's frame to the previous node's frame
                (``x_prev ~ H_prev_node x_node``); ``None`` for the first node, which gets the prior
                at the identity. The initial guess is ``H_world_prev @ H_prev_node``.
            information: ``(dim, dim)`` of the measurement; ``None``: isotropic ``config.sigma``.
        """
        if not self._order:
            if H_prev_node is not None:
                raise ValueError("the first node anchors the world frame: pass H_prev_node=None")
            self.anchor(node, np.eye(4))
            return
        node = self._check_new(node)
        if H_prev_node is None:
            raise ValueError(f"node {node} needs H_prev_node (only the first node takes None)")
        H_prev_node = self._check("H_prev_node", H_prev_node)
        guess = self._check("initial guess", self._last_estimate @ H_prev_node)
        factor = self.relative_factor(self._order[-1], node, H_prev_node, self.noise_model(information))
        self._insert(node, guess, factor)

    def anchor(self, node: int, H_world: np.ndarray) -> None:
        """Add the first node with the strong prior (``config.prior_sigma``) at ``H_world``: it fixes
        the world frame (:meth:`add_node` anchors the first node at the identity)."""
        node = self._check_new(node)
        if self._order:
            raise ValueError(f"node {node} cannot anchor the world: the graph already has nodes")
        H_world = self._check("anchor", H_world)
        self._segments.append(node)
        self._insert(node, H_world, self._prior_factor(self.key(node), self._to_gtsam(H_world), self._prior_noise))

    def start_segment(self, node: int, H_world_guess: np.ndarray) -> None:
        """Add ``node`` with a weak prior (``config.segment_sigma``) at ``H_world_guess`` instead of a
        link to the node before it: the first node of a new map segment."""
        node = self._check_new(node)
        guess = self._check("segment guess", H_world_guess)
        self._segments.append(node)
        self._insert(node, guess, self._prior_factor(self.key(node), self._to_gtsam(guess), self._segment_noise))

    def add_loop(self, i: int, j: int, H_i_j: np.ndarray, information: np.ndarray | None = None) -> None:
        """Add a loop factor ``x_i ~ H_i_j x_j`` between already added nodes ``i != j``.

        Uses ``BackendConfig.loop_kernel`` (none / Huber / Cauchy, width in whitened units). With
        ``revisit_priors``, a loop whose older node lies on a cycle an earlier loop
        closed reaches iSAM2 as a prior on the newer node (:meth:`revisit_prior`); the final polish
        still optimizes it between the two nodes.
        """
        i, j, H_i_j = self._check_loop(i, j, H_i_j)
        noise = self.noise_model(information, loop=True)
        exact = self.relative_factor(i, j, H_i_j, noise)
        if self.is_revisit(i, j):
            newer, prior, moved = self.revisit_prior(i, j, H_i_j, information)
            self._push(self._prior_factor(self.key(newer), self._to_gtsam(prior), self.noise_model(moved, loop=True)),
                       exact)
            self._pending_revisits += 1
            self.num_revisit_priors += 1
            self._pending_loop_keys.append(self.key(newer))
        else:
            self._push(exact)
            self._pending_spans.append(tuple(sorted((self._rank[i], self._rank[j]))))
        self._pending_loops += 1
        self.num_loops += 1

    def _check_loop(self, i: int, j: int, H_i_j: np.ndarray) -> tuple[int, int, np.ndarray]:
        i, j = self._check_id(i), self._check_id(j)
        for node in (i, j):
            if node not in self._known:
                raise ValueError(f"loop refers to node {node}, which was not added")
        if i == j:
            raise ValueError(f"a loop needs two different nodes, got {i} twice")
        return i, j, self._check("H_i_j", H_i_j)

    def is_revisit(self, i: int, j: int) -> bool:
        """Whether iSAM2 takes the loop between ``i`` and ``j`` as a prior on the newer node: with
        ``revisit_priors``, when the older node is optimized (not pending) and lies on a cycle that
        an earlier loop closed (between the two ends of that loop, in insertion order).

        Why: a map that revisits its places lap after lap, every lap tied to the others by loops,
        is a grid whose Bayes tree cliques grow with the number of laps, and with them the cost of
        every loop update. A place already closed into the
        map has settled; tying a revisit to it as a prior keeps iSAM2's graph a chain with unary
        factors. The first loop over a stretch of the map still enters exactly and corrects it."""
        if not self.revisit_priors:
            return False
        older = min((i, j), key=self._rank.__getitem__)
        return not self._pending_values.exists(self.key(older)) and self._closed.contains(self._rank[older])

    def revisit_prior(self, i: int, j: int, H_i_j: np.ndarray,
                      information: np.ndarray | None) -> tuple[int, np.ndarray, np.ndarray | None]:
        """The loop ``x_i ~ H_i_j x_j`` as a prior on its newer node, the older held at its estimate.

        Returns ``(newer, prior (4, 4), information)``. The between factor says
        ``X_j^-1 X_i = H_i_j^-1 exp(xi)`` (module doc); with ``X_i`` known that is
        ``X_j = X_i H_i_j exp(-Ad(H_i_j^-1) xi)``, a prior at ``X_i H_i_j`` whose information is moved
        by that adjoint; with ``X_j`` known, ``X_i = X_j H_i_j^-1 exp(xi)`` keeps it as it is.
        """
        older = min((i, j), key=self._rank.__getitem__)
        X_older = self._from_gtsam(self._estimate_one(self.key(older)))
        if older == i:
            if information is None:  # the isotropic default, which the adjoint does not keep isotropic
                information = np.eye(self.dim) / self.config.sigma**2
            moved = transport_information(information, self._inverse(H_i_j), self.generators())
            return j, self._check("revisit prior", X_older @ H_i_j), moved
        return i, self._check("revisit prior", X_older @ self._inverse(H_i_j)), information

    # ------------------------------------------------------------------ optimization
    def _live(self) -> gtsam.ISAM2:
        """iSAM2, or ``RuntimeError`` once :meth:`freeze` has dropped it."""
        if self._frozen is not None:
            raise RuntimeError("the graph was frozen at the end of its run: it takes no more factors "
                               "and has no incremental solver to ask")
        return self._isam

    @property
    def frozen(self) -> bool:
        """Whether :meth:`freeze` has dropped iSAM2."""
        return self._frozen is not None

    def freeze(self) -> bool:
        """End the graph's growth: keep iSAM2's current estimate and drop iSAM2 itself (its Bayes
        tree and linearized factors) and the copy of its factors kept for a roll-back. Those hold
        nearly all of the graph's memory (about 25 kB per keyframe node of the keyframe graph, the
        exact factors about 1 kB), which the final polish can then use. Everything that reads the
        estimate (:meth:`estimates`, :meth:`final_estimates`, :meth:`estimate`) reads the kept one
        and gives what it gave before; adding nodes or factors, updating and :meth:`loop_chi2`
        raise ``RuntimeError``. Returns whether the graph is frozen: not while factors are pending
        (an update is still to be made; nothing is dropped then). Freezing twice does nothing.
        """
        if self._frozen is not None:
            return True
        if self._pending_factors.size() or self._pending_values.size():
            return False
        self._frozen = self._isam.calculateBestEstimate() if self._isam.size() else gtsam.Values()
        self._isam = None
        self._committed_factors = gtsam.NonlinearFactorGraph()
        self._committed_values = gtsam.Values()
        return True

    def _best_estimate(self) -> gtsam.Values:
        """iSAM2's estimate of every committed node (after :meth:`freeze`, the one kept then); empty
        before the first update."""
        if self._frozen is not None:
            return self._frozen
        return self._isam.calculateBestEstimate() if self._isam.size() else gtsam.Values()

    def update(self) -> None:
        """One iSAM2 step with the pending factors; after loop closures, iterate while steps are large.

        Pure odometry: the new node's guess already satisfies its factor, so iSAM2 re-eliminates
        only the top of the Bayes tree (constant cost). Loop closures: further iSAM2 steps relinearize
        every variable whose step exceeds ``relinearize_threshold``, while some step exceeds
        ``loop_step_threshold`` (at most ``max_loop_iterations``; :meth:`_largest_step` says which
        steps are read). ``last_update_seconds`` records the wall time. If GTSAM fails (an indeterminate system),
        the pending nodes and factors are dropped, the graph is rebuilt from what it held before,
        and :class:`BackendUpdateError` says why.
        """
        start = time.perf_counter()
        iterations = 0
        if self._pending_factors.size() or self._pending_values.size():
            factors, values = self._pending_factors, self._pending_values
            # what the loop iterations watch: the whole map after a loop that closes a cycle, only the
            # nodes that revisit priors pull on when there are none of those
            loop_keys = "all" if self._pending_spans else self._pending_loop_keys
            # A loop that closes a cycle can move the whole map: keep the point iSAM2 last solved at, so
            # that a failure rebuilds the graph from there (an O(map) copy, 2 ms at 5000 nodes). A revisit
            # prior moves little: a failure starts from the failed iSAM2's own point (see _roll_back).
            before = gtsam.Values(self._isam.getLinearizationPoint()) if loop_keys == "all" else None
            try:
                iterations = self._solve(factors, values, loop_keys)
            except RuntimeError as exc:  # GTSAM's IndeterminateSystemException and relatives
                self._roll_back(before)
                first_line = next((line.strip() for line in str(exc).splitlines() if line.strip()), "")
                raise BackendUpdateError(f"{type(exc).__name__}: {first_line}") from None
            finally:
                exact, spans = self._pending_exact, self._pending_spans
                self._pending_factors = gtsam.NonlinearFactorGraph()
                self._pending_exact = gtsam.NonlinearFactorGraph()
                self._pending_values = gtsam.Values()
                self._pending_loops = self._pending_revisits = 0
                self._pending_spans, self._pending_loop_keys = [], []
            self._committed_factors.push_back(factors)
            self._exact_factors.push_back(exact)
            self._committed_values.insert(values)
            for span in spans:
                self._closed.add(*span)
            self._pending_ids = []
            if self._order:
                self._last_estimate = self._from_gtsam(self._estimate_one(self.key(self._order[-1])))
        self.last_update_iterations = iterations
        self.last_update_seconds = time.perf_counter() - start
        self.total_update_seconds += self.last_update_seconds
        self.num_updates += 1

    def _solve(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values, loop_keys: list[int] | str) -> int:
        """iSAM2 steps for one update; ``loop_keys``: the GTSAM keys whose steps decide whether to
        iterate after loops ("all": every variable's; empty: no loops, one step)."""
        self._isam.update(factors, values)
        iterations = 1
        if loop_keys:
            empty_graph, empty_values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            update_params = gtsam.ISAM2UpdateParams()
            update_params.force_relinearize = True
            while iterations < 1 + self.config.max_loop_iterations:
                if self._largest_step(loop_keys) < self.config.loop_step_threshold:
                    break
                self._isam.update(empty_graph, empty_values, update_params)
                iterations += 1
        return iterations

    def _largest_step(self, loop_keys: list[int] | str) -> float:
        """The largest entry of iSAM2's current step over ``loop_keys`` ("all": the whole map).

        A loop that closes a cycle can move any node of it, so its update watches every step (an
        O(map) read; such loops are rare once revisits are priors). A revisit prior pulls on one
        node, whose step is the largest of the correction it spreads down the chain; reading only
        it keeps the update of a revisit O(1) (the whole step vector of 5000 nodes costs 1.6 ms)."""
        delta = self._isam.getDelta()
        if loop_keys == "all":
            step = np.abs(delta.vector())
            return float(step.max()) if step.size else 0.0
        return max(float(np.abs(delta.at(key)).max()) for key in loop_keys)

    def _roll_back(self, start: gtsam.Values | None = None) -> None:
        """Forget the pending nodes and rebuild iSAM2 from the committed factors at their optimum,
        found by Gauss-Newton from ``start`` (where iSAM2 last solved them), else from where the
        failed iSAM2 had linearized them, else from their first guesses (which a long run has left
        far behind: rebuilt from those, every later update of a 300-submap lap replay failed).
        O(map), on failure only."""
        if start is None:
            start = self._committed_linearization_point()
        for node in self._pending_ids:
            self._order.remove(node)
            self._known.discard(node)
            self._rank.pop(node, None)
            if node in self._segments:
                self._segments.remove(node)
        self._pending_ids = []
        self.num_loops -= self._pending_loops
        self.num_revisit_priors -= self._pending_revisits
        self._isam = self._new_isam()
        if self._committed_factors.size():
            points = [gauss_newton(self._committed_factors, start), start] if start is not None else []
            for point in [*points, self._committed_values]:
                try:
                    self._isam.update(self._committed_factors, point)
                    break
                except RuntimeError:  # not solvable there: the next point, on a fresh iSAM2
                    self._isam = self._new_isam()
        self._last_estimate = (self._from_gtsam(self._estimate_one(self.key(self._order[-1])))
                               if self._order else None)

    def _committed_linearization_point(self) -> gtsam.Values | None:
        """The committed nodes' values in the (failed) iSAM2, or ``None`` if any is missing or not finite."""
        try:
            point = self._isam.getLinearizationPoint()
            values = gtsam.Values()
            for key in self._committed_values.keys():
                element = self._at(point, key)
                if not np.all(np.isfinite(self._from_gtsam(element))):
                    return None
                values.insert(key, element)
            return values
        except (RuntimeError, ValueError):  # ValueError: a node the failed step left degenerate
            return None

    # ------------------------------------------------------------------ results
    def estimate(self, node: int) -> np.ndarray:
        """Current estimate of one node, (4, 4) float64 (its initial guess until :meth:`update`)."""
        node = self._check_id(node)
        if node not in self._known:
            raise KeyError(f"node {node} was not added")
        key = self.key(node)
        if self._pending_values.exists(key):
            return self._from_gtsam(self._at(self._pending_values, key))
        return self._from_gtsam(self._estimate_one(key))

    def estimates(self) -> dict[int, np.ndarray]:
        """``{node: (4, 4) float64}`` for every node, in insertion order.

        Costs O(number of nodes) (a full back-substitution); nodes added since the last
        :meth:`update` report their initial guess.
        """
        values = self._best_estimate()
        out: dict[int, np.ndarray] = {}
        for node in self._order:
            key = self.key(node)
            source = self._pending_values if self._pending_values.exists(key) else values
            out[node] = self._from_gtsam(self._at(source, key))
        return out

    def final_estimates(self, max_iterations: int = 20) -> dict[int, np.ndarray]:
        """Like :meth:`estimates`, polished to convergence by batch Gauss-Newton on the whole graph.

        Starts at iSAM2's estimate (which is within about the relinearization threshold of the
        optimum, so one or two iterations suffice: about 40 ms for 300 SL(4) nodes) and keeps
        each step only if it lowers the graph error. iSAM2's own state is not changed, so the graph
        can keep growing afterwards. Costs O(number of nodes): meant for the end of a run.
        """
        if self._pending_factors.size() or self._pending_values.size():
            self.update()
        start = self._best_estimate()  # one back-substitution, read once
        if not start.size():
            return self.estimates()
        values = self.polished_values(max_iterations, start=start)
        return {node: self._from_gtsam(self._at(values, self.key(node))) for node in self._order}

    def polished_values(self, max_iterations: int = 20, start: gtsam.Values | None = None) -> gtsam.Values:
        """iSAM2's estimate (or ``start``, when it is that estimate already read) polished by batch
        Gauss-Newton on :meth:`factor_graph` (see :meth:`final_estimates`), as ``gtsam.Values``.

        Within ``BackendConfig.polish_memory_mib`` (estimated by :func:`polish_blocks` from the
        graph's structure) the whole graph is polished at once: its optimum. A graph whose polish
        would take more (a long run that revisits its places lap after lap, every lap tied to the
        others) is polished in consecutive blocks of nodes, oldest first, each with the factors
        whose newest node it holds and the older nodes they reach held at their polished values;
        :attr:`polish_block_count` says how many it took.
        """
        start = self._best_estimate() if start is None else start
        graph = self.factor_graph()
        budget = int(self.config.polish_memory_mib) * 2**20
        self.polish_block_count = 1
        if budget <= 0 or dense_polish_bytes(len(self._order), self.dim) <= budget:  # fits whatever its structure
            return gauss_newton(graph, start, max_iterations)
        factor_keys = [tuple(graph.at(i).keys()) for i in range(graph.size())]
        rank = {self.key(node): r for r, node in enumerate(self._order)}
        newest = np.array([max(rank[k] for k in keys) for keys in factor_keys], dtype=np.int64)
        order = np.argsort(newest, kind="stable")
        blocks = polish_blocks(newest[order], [factor_keys[i] for i in order], len(self._order), self.dim, budget)
        self.polish_block_count = len(blocks)
        if len(blocks) == 1:
            return gauss_newton(graph, start, max_iterations)
        values = gtsam.Values(start)
        keys = [self.key(node) for node in self._order]
        cuts = np.searchsorted(newest[order], [b for _, b in blocks])
        for (a, b), lo, hi in zip(blocks, [0, *cuts[:-1]], cuts):
            block = gtsam.NonlinearFactorGraph()
            block_values = gtsam.Values()
            for key in keys[a:b]:
                block_values.insert(key, self._at(values, key))
            for i in order[lo:hi]:
                block.add(graph.at(int(i)))
                for key in factor_keys[i]:
                    if rank[key] < a and not block_values.exists(key):  # an older node: held where it is
                        held = self._at(values, key)
                        block_values.insert(key, held)
                        block.add(self._equality_factor(key, held))
            polished = gauss_newton(block, block_values, max_iterations)
            for key in keys[a:b]:
                values.update(key, self._at(polished, key))
        return values

    def isam_values(self) -> gtsam.Values:
        """iSAM2's current estimate as ``gtsam.Values`` (keys :meth:`key`; nodes added since the last
        :meth:`update` are not in it), e.g. to start a batch optimizer of :meth:`factor_graph` from."""
        return self._best_estimate()

    def matrices_in(self, values: gtsam.Values) -> dict[int, np.ndarray]:
        """``{node: (4, 4) float64}`` every node's matrix as ``values`` hold it (e.g. a batch
        optimizer's result over :meth:`factor_graph`), in insertion order."""
        return {node: self._from_gtsam(self._at(values, self.key(node))) for node in self._order}

    def loop_chi2(self, i: int, j: int, H_i_j: np.ndarray, information: np.ndarray) -> float:
        """Squared Mahalanobis distance of the loop ``H_i_j`` between nodes ``i`` and ``j`` from the
        current estimate, under the two nodes' joint covariance plus the measurement's own
        (``information^-1``; see ``sl4slam.backend.interface.Backend.loop_chi2``). The joint covariance comes from iSAM2's Bayes
        tree (equal to a batch marginalization of the whole graph to 1e-11, and far cheaper; decision:
        docs/decisions/isam2.md), so call it for loop candidates only.
        A revisit (:meth:`is_revisit`) is tested as iSAM2 would take it: the prior on the newer node
        against that node's marginal, the older held at its estimate."""
        i, j, H_i_j = self._check_loop(i, j, H_i_j)
        unit = gtsam.noiseModel.Unit.Create(self.dim)
        if self.is_revisit(i, j):
            newer, prior, moved = self.revisit_prior(i, j, H_i_j, information)
            factor, keys = self._prior_factor(self.key(newer), self._to_gtsam(prior), unit), [self.key(newer)]
            information = moved
        else:
            factor, keys = self.relative_factor(i, j, H_i_j, unit), [self.key(j), self.key(i)]
        values = gtsam.Values()  # the nodes the factor reads: a full estimate costs O(map) per candidate
        for key in keys:
            values.insert(key, self._estimate_one(key))
        A, _ = factor.linearize(values).jacobian()
        order = list(factor.keys())
        if order != keys:  # jacobian blocks follow the factor's key order
            A = np.concatenate([A[:, order.index(k) * self.dim:(order.index(k) + 1) * self.dim] for k in keys], axis=1)
        isam = self._live()
        joint = (isam.marginalCovariance(keys[0]) if len(keys) == 1
                 else isam.jointMarginalCovariance(keys).fullMatrix())
        covariance = A @ joint @ A.T + np.linalg.inv(information)
        error = np.asarray(factor.unwhitenedError(values), dtype=np.float64)
        return float(error @ np.linalg.solve(covariance, error))

    def factor_graph(self) -> gtsam.NonlinearFactorGraph:
        """The factors optimized so far (priors, odometry, loops), every loop between its two nodes
        (as the final polish optimizes them), e.g. for a batch comparison."""
        return gtsam.NonlinearFactorGraph(self._exact_factors)

    @property
    def num_nodes(self) -> int:
        return len(self._order)

    @property
    def node_ids(self) -> list[int]:
        """Every node, in insertion order."""
        return list(self._order)

    @property
    def segments(self) -> list[int]:
        """First node of every map segment (the first is the first node's)."""
        return list(self._segments)

