"""Weights-free ORB loop-closure retrieval."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sl4slam.config import RetrievalConfig
from sl4slam.errors import UserError
from sl4slam.retrieval.orb import OrbRetrieval, match_descriptors
from sl4slam.types import LoopCandidate, Retrieval
from sl4slam.io.memory import frames_from_images as as_frames

DISTRACTOR_BASE = 1000


@pytest.fixture(scope="module")
def tum(shared_dir) -> list[np.ndarray]:
    """The 37 RGB frames of the real TUM fr1_xyz excerpt, ``(480, 640, 3)`` uint8 each."""
    root = shared_dir / "data/tum_rgbd_fr1_xyz_first37"
    lines = [line.split() for line in (root / "rgb.txt").read_text().splitlines()]
    paths = [root / fields[1] for fields in lines if fields and not fields[0].startswith("#")]
    return [cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB) for path in paths]


def random_texture(seed: int, shape=(480, 640, 3)) -> np.ndarray:
    """Seeded multi-scale random texture: many ORB features, no relation to any other image."""
    rng = np.random.default_rng(seed)
    texture = np.zeros(shape, np.float32)
    for sigma in (1.0, 3.0, 8.0):
        layer = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma)
        texture += layer / layer.std()
    return np.clip(128 + 30 * texture, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def distractors() -> list[np.ndarray]:
    return [random_texture(seed) for seed in range(6)]


def mild_warp(image: np.ndarray) -> np.ndarray:
    """``image`` seen under a mild homography (rotation 4 deg, scale 0.93, shift, slight perspective)."""
    height, width = image.shape[:2]
    rotation = cv2.getRotationMatrix2D((width / 2, height / 2), 4.0, 0.93)
    homography = np.vstack([rotation, [2e-5, -1e-5, 1.0]])
    homography[:2, 2] += (12.0, -7.0)
    return cv2.warpPerspective(image, homography, (width, height), borderMode=cv2.BORDER_REFLECT)


def test_is_a_retrieval():
    retrieval = OrbRetrieval(RetrievalConfig())
    assert isinstance(retrieval, Retrieval)
    assert retrieval.name == "orb"
    assert len(retrieval) == 0
    assert retrieval.query(as_frames([0], [random_texture(0)]), submap_id=10, max_results=1) == []


def test_match_descriptors_finds_planted_pairs():
    rng = np.random.default_rng(4)
    stored = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    permutation = rng.permutation(50)[:20]
    query = np.concatenate([stored[permutation], rng.integers(0, 256, (10, 32), dtype=np.uint8)])
    query[:20, 0] ^= 0b00000111  # 3 flipped bits: still a clear nearest neighbour
    query_idx, stored_idx = match_descriptors(query, stored, ratio=0.8, max_hamming=64)
    # The 10 unrelated descriptors (~128 bits from everything) fail the ratio test and the bound.
    np.testing.assert_array_equal(query_idx, np.arange(20))
    np.testing.assert_array_equal(stored_idx, permutation)


def test_match_descriptors_drops_ambiguous_claims():
    rng = np.random.default_rng(5)
    stored = rng.integers(0, 256, (30, 32), dtype=np.uint8)
    query = stored[[3, 3, 7]].copy()  # two query descriptors claim stored 3
    query[1, 5] ^= 0b1
    query_idx, stored_idx = match_descriptors(query, stored, ratio=0.8, max_hamming=64)
    np.testing.assert_array_equal(query_idx, [2])
    np.testing.assert_array_equal(stored_idx, [7])
    # The Hamming search is exact: the nearest neighbour of an exact copy is itself.
    query_idx, stored_idx = match_descriptors(stored, stored, ratio=0.8, max_hamming=0)
    np.testing.assert_array_equal(stored_idx, np.arange(30))


def test_extracted_features_are_compact(tum):
    retrieval = OrbRetrieval(RetrievalConfig(orb_features=500))
    features = retrieval.extract(tum[0])
    assert 400 <= len(features) <= 500
    assert features.keypoints.dtype == np.float32 and features.keypoints.shape == (len(features), 2)
    assert features.descriptors.dtype == np.uint8 and features.descriptors.shape == (len(features), 32)
    assert features.word_tf.sum() == pytest.approx(1.0, abs=1e-5)
    assert np.all(np.diff(features.word_ids) > 0)
    # Large inputs are processed at the working resolution.
    big = cv2.resize(tum[0], (1280, 960))
    assert retrieval.extract(big).keypoints.max(axis=0)[0] < 640


def test_revisit_is_found(tum, distractors):
    config = RetrievalConfig()
    retrieval = OrbRetrieval(config)
    retrieval.add(as_frames([0], [tum[0]]), submap_id=0)
    retrieval.add(as_frames(list(range(DISTRACTOR_BASE, DISTRACTOR_BASE + 3)), distractors[:3]), submap_id=0)
    retrieval.add(as_frames(list(range(DISTRACTOR_BASE + 3, DISTRACTOR_BASE + 6)), distractors[3:]), submap_id=1)
    assert len(retrieval) == 7
    for query_frame in (3, 20):
        found = retrieval.query(as_frames([query_frame], [tum[query_frame]]), submap_id=3, max_results=1)
        assert len(found) == 1
        candidate = found[0]
        assert (candidate.query_frame, candidate.match_frame, candidate.match_submap) == (query_frame, 0, 0)
        assert 0.0 <= candidate.distance < 1.0 - config.orb_min_inliers / config.orb_features
    # A nearer view verifies more matches, so it is closer.
    near = retrieval.query(as_frames([3], [tum[3]]), submap_id=3, max_results=1)[0]
    far = retrieval.query(as_frames([20], [tum[20]]), submap_id=3, max_results=1)[0]
    assert near.distance < far.distance


def test_verification_stops_once_enough_queries_match(tum, distractors, monkeypatch):
    retrieval = OrbRetrieval(RetrievalConfig(orb_candidates=5))
    retrieval.add(as_frames([0, 36], [tum[0], tum[36]]), submap_id=0)
    retrieval.add(as_frames(list(range(DISTRACTOR_BASE, DISTRACTOR_BASE + 4)), distractors[:4]), submap_id=1)
    verified: list[int] = []
    verify = retrieval.verify
    monkeypatch.setattr(retrieval, "verify", lambda query, position: verified.append(position) or verify(query, position))
    queries, images = [2, 34], [tum[2], tum[34]]
    one = retrieval.query(as_frames(queries, images), submap_id=4, max_results=1)
    assert len(one) == 1 and len(verified) == 1  # the most similar pair verified: nothing more spent
    verified.clear()
    both = retrieval.query(as_frames(queries, images), submap_id=4, max_results=5)
    assert len(verified) == 5  # every query may still match: the whole budget
    assert {(c.query_frame, c.match_frame) for c in both} == {(2, 0), (34, 36)}
    assert one[0] in both


def test_warped_copy_is_found(tum, distractors):
    retrieval = OrbRetrieval(RetrievalConfig())
    retrieval.add(as_frames([DISTRACTOR_BASE, DISTRACTOR_BASE + 1], distractors[:2]), submap_id=0)
    retrieval.add(as_frames([0], [tum[0]]), submap_id=1)
    found = retrieval.query(as_frames([99], [mild_warp(tum[0])]), submap_id=5, max_results=3)
    assert [(c.query_frame, c.match_frame, c.match_submap) for c in found] == [(99, 0, 1)]


def test_unrelated_images_are_rejected(tum, distractors):
    retrieval = OrbRetrieval(RetrievalConfig())
    retrieval.add(as_frames([0, 18, 36], [tum[0], tum[18], tum[36]]), submap_id=0)
    retrieval.add(as_frames(list(range(DISTRACTOR_BASE, DISTRACTOR_BASE + 4)), distractors[:4]), submap_id=1)
    unrelated = distractors[4:] + [random_texture(100, (600, 500, 3))]
    for offset, image in enumerate(unrelated):
        assert retrieval.query(as_frames([2000 + offset], [image]), submap_id=9, max_results=5) == []
    # Same texture statistics, different content: the verification sees almost nothing.
    query_features = retrieval.extract(distractors[5])
    inliers = [retrieval.verify(query_features, position) for position in range(len(retrieval))]
    assert max(inliers) < RetrievalConfig().orb_min_inliers // 2
    # A TUM frame is not matched to a texture database.
    textures_only = OrbRetrieval(RetrievalConfig())
    textures_only.add(as_frames(list(range(DISTRACTOR_BASE, DISTRACTOR_BASE + 6)), distractors), submap_id=0)
    assert textures_only.query(as_frames([3], [tum[3]]), submap_id=9, max_results=5) == []


def test_unrelated_natural_image_is_rejected(tum):
    cbook = pytest.importorskip("matplotlib.cbook")
    try:
        with cbook.get_sample_data("grace_hopper.jpg") as handle:
            data = np.frombuffer(handle.read(), np.uint8)
    except (OSError, ValueError):
        pytest.skip("matplotlib sample image absent")
    portrait = cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    retrieval = OrbRetrieval(RetrievalConfig())
    retrieval.add(as_frames([0, 18, 36], [tum[0], tum[18], tum[36]]), submap_id=0)
    assert retrieval.query(as_frames([500], [portrait]), submap_id=9, max_results=5) == []
    retrieval.add(as_frames([500], [portrait]), submap_id=1)
    assert retrieval.query(as_frames([3], [tum[3]]), submap_id=9, max_results=5)[0].match_frame == 0


def test_tau_interval_excludes_recent_submaps(tum):
    retrieval = OrbRetrieval(RetrievalConfig(tau_interval=2))
    retrieval.add(as_frames([0], [tum[0]]), submap_id=1)
    # Submap 1 is eligible from submap 4 on: 1 <= submap_id - 1 - 2.
    for submap_id in (1, 2, 3):
        assert retrieval.query(as_frames([3], [tum[3]]), submap_id=submap_id, max_results=1) == []
    assert retrieval.query(as_frames([3], [tum[3]]), submap_id=4, max_results=1)[0].match_frame == 0

    no_gap = OrbRetrieval(RetrievalConfig(tau_interval=0))
    no_gap.add(as_frames([0], [tum[0]]), submap_id=1)
    assert no_gap.query(as_frames([3], [tum[3]]), submap_id=1, max_results=1) == []
    assert no_gap.query(as_frames([3], [tum[3]]), submap_id=2, max_results=1)[0].match_submap == 1


def test_results_are_sorted_truncated_and_deterministic(tum, distractors):
    def run() -> tuple[list[LoopCandidate], list[LoopCandidate]]:
        retrieval = OrbRetrieval(RetrievalConfig(), seed=5)
        retrieval.add(as_frames([0, DISTRACTOR_BASE], [tum[0], distractors[0]]), submap_id=0)
        retrieval.add(as_frames([12, DISTRACTOR_BASE + 1], [tum[12], distractors[1]]), submap_id=1)
        queries = [30, 2, 24, DISTRACTOR_BASE + 2]
        images = [tum[30], tum[2], tum[24], distractors[2]]
        every = retrieval.query(as_frames(queries, images), submap_id=4, max_results=10)
        best_two = retrieval.query(as_frames(queries, images), submap_id=4, max_results=2)
        retrieval.add(as_frames(queries, images), submap_id=4)  # reuses the query's features
        assert len(retrieval) == 8
        return every, best_two

    every, best_two = run()
    assert sorted(c.query_frame for c in every) == [2, 24, 30]  # one candidate per matched query; none for the texture
    assert [c.distance for c in every] == sorted(c.distance for c in every)
    assert best_two == every[:2]
    assert every[0].query_frame == 2 and every[0].match_frame == 0  # two frames apart: the strongest
    assert {c.match_frame for c in every} <= {0, 12}
    assert run() == (every, best_two)
    retrieval = OrbRetrieval(RetrievalConfig())
    retrieval.add(as_frames([0], [tum[0]]), submap_id=0)
    assert retrieval.query(as_frames([2], [tum[2]]), submap_id=4, max_results=0) == []


def test_add_reuses_the_query_features_only_for_the_same_image(tum):
    retrieval = OrbRetrieval(RetrievalConfig())
    retrieval.query(as_frames([7], [tum[7]]), submap_id=0, max_results=1)
    extracted = retrieval.describe_seconds
    retrieval.add(as_frames([7], [tum[7].copy()]), submap_id=0)  # equal pixels, another array: reused
    assert retrieval.describe_seconds == extracted
    stored = retrieval._stored_features(len(retrieval) - 1)[1]

    changed = tum[8].copy()
    retrieval.query(as_frames([9], [changed]), submap_id=1, max_results=1)
    changed[:] = tum[20]  # modified in place between query and add: extracted again
    extracted = retrieval.describe_seconds
    retrieval.add(as_frames([9], [changed]), submap_id=1)
    assert retrieval.describe_seconds > extracted
    assert np.array_equal(retrieval._stored_features(len(retrieval) - 1)[1], retrieval.extract(tum[20]).descriptors)
    assert not np.array_equal(retrieval._stored_features(len(retrieval) - 1)[1], stored)


def test_bad_input_is_a_user_error(tum):
    retrieval = OrbRetrieval(RetrievalConfig())
    with pytest.raises(UserError):
        retrieval.add(as_frames([0, 1], [tum[0]]), submap_id=0)
    with pytest.raises(UserError):
        retrieval.add(as_frames([0], [tum[0].astype(np.float32)]), submap_id=0)
    with pytest.raises(UserError):
        OrbRetrieval(RetrievalConfig(orb_candidates=0))


def test_similarity_matches_dense_tf_idf():
    """The inverted-file scoring (and its row-wise tail) equals a dense tf-idf cosine computed directly."""
    retrieval = OrbRetrieval(RetrievalConfig(orb_features=300))
    images = [random_texture(seed, (160, 200, 3)) for seed in range(200, 345)]
    stored = [retrieval.extract(image) for image in images]
    queries = [stored[3], retrieval.extract(random_texture(999, (160, 200, 3)))]

    def dense_reference(count: int, idf_count: int | None = None) -> np.ndarray:
        # Dense over the words that occur (the full vocabulary is 2**18 wide); idf from the first
        # idf_count keyframes (the index refreshes it only when the database grew by a quarter).
        idf_count = count if idf_count is None else idf_count
        words = np.unique(np.concatenate([f.word_ids for f in stored + queries]))
        tf = np.zeros((count, len(words)))
        for row, features in enumerate(stored[:count]):
            tf[row, np.searchsorted(words, features.word_ids)] = features.word_tf
        idf = np.log1p(idf_count / np.maximum((tf[:idf_count] > 0).sum(axis=0), 1))
        query_tf = np.zeros((len(queries), len(words)))
        for row, features in enumerate(queries):
            query_tf[row, np.searchsorted(words, features.word_ids)] = features.word_tf
        a, b = tf * idf, query_tf * idf
        return (a @ b.T) / (np.linalg.norm(a, axis=1)[:, None] * np.linalg.norm(b, axis=1)[None, :])

    retrieval.add(as_frames(list(range(70)), images[:70]), submap_id=0)
    np.testing.assert_allclose(retrieval.similarity(queries), dense_reference(70), rtol=1e-4, atol=1e-6)
    retrieval.add(as_frames(list(range(70, 75)), images[70:75]), submap_id=1)  # scored row-wise, after the inverted file
    similarity = retrieval.similarity(queries)
    np.testing.assert_allclose(similarity, dense_reference(75, idf_count=70), rtol=1e-4, atol=1e-6)
    assert int(np.argmax(similarity[:, 0])) == 3 and similarity[3, 0] == pytest.approx(1.0, abs=1e-5)
    # a query after every few keyframes: the idf is rebuilt once the database has grown by more than
    # max(64, a quarter) keyframes since it was computed (at 135 here), not from the first ones forever
    for start in range(75, 145, 10):
        retrieval.add(as_frames(list(range(start, start + 10)), images[start:start + 10]), submap_id=start)
        similarity = retrieval.similarity(queries)
        np.testing.assert_allclose(similarity, dense_reference(start + 10, idf_count=70 if start + 10 < 135 else 135),
                                   rtol=1e-4, atol=1e-6)


def test_coarse_ranking_keeps_the_revisit_in_a_large_database():
    """Past COARSE_CANDIDATES stored keyframes, queries are ranked coarsely first (hashed words, one
    matrix product); the exact scores of the surviving rows equal the full tf-idf ones."""
    from sl4slam.retrieval.orb import COARSE_CANDIDATES

    retrieval = OrbRetrieval(RetrievalConfig(orb_features=500))
    images = [random_texture(seed, (240, 320, 3)) for seed in range(300, 300 + 4 * COARSE_CANDIDATES + 8)]
    retrieval.add(as_frames(list(range(len(images))), images), submap_id=0)
    target = 2 * COARSE_CANDIDATES + 5
    query = mild_warp(images[target])
    found = retrieval.query(as_frames([10_000], [query]), submap_id=5, max_results=1)
    assert [c.match_frame for c in found] == [target]
    features = [retrieval.extract(query)]
    rows = np.arange(len(images))
    np.testing.assert_allclose(retrieval.similarity_rows(features, rows), retrieval.similarity(features), rtol=1e-5, atol=1e-7)


def test_stored_words_decode_to_the_extracted_term_frequencies():
    """The compact word rows give back exactly (bit for bit) the word ids and term frequencies of
    extract(), for consecutive rows and for any selection of rows."""
    retrieval = OrbRetrieval(RetrievalConfig(orb_features=300))
    stripes = np.zeros((160, 200, 3), np.uint8)
    stripes[:, ::6] = 255  # repetitive: words that occur several times
    images = [random_texture(seed, (160, 200, 3)) for seed in range(400, 420)] + [stripes, np.zeros((160, 200, 3), np.uint8)]
    retrieval.add(as_frames(list(range(len(images))), images), submap_id=0)
    extracted = [retrieval.extract(image) for image in images]
    assert max(f.word_tf.max(initial=0) * 4 * len(f) for f in extracted) > 1.5  # some word counted twice
    for rows in (np.arange(len(images)), np.array([21, 3, 20, 0, 7]), np.array([], np.int64)):
        data, indices, indptr = retrieval._entries(rows)
        assert data.dtype == np.float32 and indices.dtype == np.int32 and indptr.dtype == np.int64
        expected = [extracted[row] for row in rows]
        assert data.tobytes() == np.concatenate([f.word_tf for f in expected] + [np.zeros(0, np.float32)]).tobytes()
        assert indices.tobytes() == np.concatenate([f.word_ids for f in expected] + [np.zeros(0, np.int32)]).tobytes()
        np.testing.assert_array_equal(np.diff(indptr), [len(f.word_ids) for f in expected])


def test_a_rewound_database_with_spilled_features_answers_like_a_fresh_one(tmp_path):
    """Rewinding withdraws the newest keyframes from every buffer (words, large steps, global rows,
    features in RAM); keyframes added after it overwrite them, and the database then answers byte
    for byte as one that never held the withdrawn keyframes."""
    config = RetrievalConfig(orb_features=300)
    images = [random_texture(seed, (160, 200, 3)) for seed in range(500, 524)]
    kept, withdrawn, added = images[:12], images[12:18], images[18:]
    rewound, fresh = OrbRetrieval(config), OrbRetrieval(config)
    rewound.spill_features(tmp_path / "rewound", 8)  # the withdrawn six stay in RAM
    fresh.spill_features(tmp_path / "fresh", 8)
    for retrieval in (rewound, fresh):
        for submap in range(3):
            retrieval.add(as_frames(list(range(4 * submap, 4 * submap + 4)), kept[4 * submap : 4 * submap + 4]), submap)
    mark = rewound.mark()
    rewound.add(as_frames(list(range(100, 106)), withdrawn), 3)
    queries = [rewound.extract(mild_warp(image)) for image in images[::5]]
    rewound.similarity(queries)  # caches (idf, norms, inverted file) that include the withdrawn keyframes
    rewound.rewind(mark)
    for retrieval in (rewound, fresh):
        retrieval.add(as_frames(list(range(200, 206)), added), 3)
    assert len(rewound) == len(fresh) == 18 and rewound.features_in_ram() == fresh.features_in_ram() == 8
    rows = np.arange(18)
    for got, want in zip(rewound._entries(rows), fresh._entries(rows)):
        assert got.tobytes() == want.tobytes()
    assert rewound._global[:18].tobytes() == fresh._global[:18].tobytes()
    assert rewound._group_sums[:1].tobytes() == fresh._group_sums[:1].tobytes()  # written again with rows 12-15
    np.testing.assert_array_equal(rewound._document_frequency, fresh._document_frequency)
    for position in range(18):
        for got, want in zip(rewound._stored_features(position), fresh._stored_features(position)):
            assert got.tobytes() == want.tobytes()
    assert rewound.similarity(queries).tobytes() == fresh.similarity(queries).tobytes()
    assert rewound.similarity_rows(queries, rows[::-1]).tobytes() == fresh.similarity_rows(queries, rows[::-1]).tobytes()
    probes = as_frames(list(range(300, 304)), [mild_warp(image) for image in images[:24:6]])
    assert rewound.query(probes, 9, 4) == fresh.query(probes, 9, 4)
    for retrieval in (rewound, fresh):  # the coarse ranking by groups (forced) reads the rewritten group
        retrieval.config = RetrievalConfig(orb_features=300, orb_coarse_flat_rows=0, orb_coarse_groups=1)
    assert rewound.query(probes, 9, 4) == fresh.query(probes, 9, 4)


def hashed_rows(count: int, seed: int) -> np.ndarray:
    """``(count, GLOBAL_DIM)`` float32 rows like the stored hashed ones: non-negative, unit length."""
    from sl4slam.retrieval.orb import GLOBAL_DIM

    rows = np.random.default_rng(seed).gamma(0.5, size=(count, GLOBAL_DIM)).astype(np.float32)
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def database_of_rows(rows: np.ndarray, **settings) -> OrbRetrieval:
    """A retrieval whose stored hashed rows are ``rows`` (only the coarse ranking reads them)."""
    retrieval = OrbRetrieval(RetrievalConfig(**settings))
    for position, row in enumerate(rows):
        retrieval._append_global_row(position, row)
    return retrieval


def test_group_sums_are_the_sums_of_each_finished_group_of_rows():
    from sl4slam.retrieval.orb import GROUP_ROWS

    rows = hashed_rows(5 * GROUP_ROWS + 7, seed=0)
    retrieval = database_of_rows(rows)
    assert len(retrieval._group_sums) >= 5
    for group in range(5):
        expected = rows[group * GROUP_ROWS:(group + 1) * GROUP_ROWS].sum(axis=0, dtype=np.float64).astype(np.float32)
        assert retrieval._group_sums[group].tobytes() == expected.tobytes()
    assert not retrieval._group_sums[5:].any()  # the unfinished sixth group has no sum yet


def test_coarse_ranking_by_groups_keeping_every_group_is_the_flat_ranking():
    """With as many groups kept as there are, the grouped ranking scores every row: the same rows."""
    from sl4slam.retrieval.orb import GROUP_ROWS

    rows = hashed_rows(12 * GROUP_ROWS + 5, seed=1)
    queries = hashed_rows(17, seed=2)
    eligible = np.arange(len(rows))
    flat = database_of_rows(rows, orb_coarse_flat_rows=len(rows)).coarse_rows(queries, eligible)
    grouped = database_of_rows(rows, orb_coarse_flat_rows=0, orb_coarse_groups=12).coarse_rows(queries, eligible)
    assert grouped.tobytes() == flat.tobytes()
    assert np.all(np.diff(flat) > 0)  # ascending, no repeats


def test_coarse_ranking_goes_by_groups_only_past_the_flat_rows():
    """Up to ``orb_coarse_flat_rows`` eligible rows every row is scored; one more and only the rows
    of each query's best groups (and the unfinished last group) are."""
    from sl4slam.retrieval.orb import COARSE_CANDIDATES, GROUP_ROWS

    rows = hashed_rows(40 * GROUP_ROWS + 3, seed=3)
    queries = hashed_rows(4, seed=4)
    eligible = np.arange(len(rows))
    flat = database_of_rows(rows, orb_coarse_flat_rows=10**9).coarse_rows(queries, eligible)
    at_bound = database_of_rows(rows, orb_coarse_flat_rows=len(rows), orb_coarse_groups=1)
    assert at_bound.coarse_rows(queries, eligible).tobytes() == flat.tobytes()
    past = database_of_rows(rows, orb_coarse_flat_rows=len(rows) - 1, orb_coarse_groups=1)
    grouped = past.coarse_rows(queries, eligible)
    scores = past._group_sums[:40] @ queries.T
    allowed = set(np.argmax(scores, axis=0).tolist()) | {40}  # each query's best group, and the tail
    assert set((grouped // GROUP_ROWS).tolist()) <= allowed
    assert grouped.tobytes() != flat.tobytes()  # the flat ranking's best rows lie in other groups too
    assert len(grouped) <= len(queries) * COARSE_CANDIDATES
    not_a_prefix = eligible[1:]  # eligible rows that are not the first stored ones: scored one by one
    expected = np.unique(not_a_prefix[np.argpartition(-(rows[1:] @ queries.T), COARSE_CANDIDATES - 1,
                                                      axis=0)[:COARSE_CANDIDATES]])
    assert past.coarse_rows(queries, not_a_prefix).tobytes() == expected.tobytes()


def test_coarse_ranking_by_groups_finds_the_revisit():
    """Forced through the groups (one kept per query), a revisit of a keyframe in the middle of a
    database of many groups is found, as with the flat ranking. Each group is a camera panning
    over one surface (overlapping crops of one texture), as consecutive keyframes of a video are."""
    from sl4slam.retrieval.orb import GROUP_ROWS

    images = []
    for group in range(12):
        surface = random_texture(600 + group, (240, 320 + 8 * GROUP_ROWS, 3))
        images += [surface[:, 8 * k:8 * k + 320] for k in range(GROUP_ROWS)]
    target = 5 * GROUP_ROWS + 9
    probe = as_frames([10_000], [mild_warp(images[target])])
    found = {}
    for flat_rows in (10**9, 0):
        retrieval = OrbRetrieval(RetrievalConfig(orb_features=500, orb_coarse_flat_rows=flat_rows, orb_coarse_groups=1))
        for submap in range(12):
            first = submap * GROUP_ROWS
            retrieval.add(as_frames(list(range(first, first + GROUP_ROWS)), images[first:first + GROUP_ROWS]), submap)
        found[flat_rows] = retrieval.query(probe, submap_id=20, max_results=1)
    assert [c.match_frame for c in found[0]] == [target]
    assert found[0] == found[10**9]
