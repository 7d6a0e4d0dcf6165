import numpy as np

from coopd.geometry import euler_to_matrix, rigid
from coopd.grid import transform_grid
from coopd.merging import yaw_search
from coopd.merging.level import level_transform
from coopd.merging.params import coopd_params


def test_levelling_undoes_a_known_tilt(near_pair):
    """level L maps the world's up, seen in the map frame, to +z: up_map = L^T z. Tilting the grid by
    a known rotation must tilt the up vector found by the same rotation."""
    z = np.array([0.0, 0.0, 1.0])
    tilt = euler_to_matrix(np.radians(2.0), np.radians(-1.5), 0.0)
    tilted = transform_grid(near_pair.a, rigid(tilt))
    up_a = level_transform(near_pair.a, 50)[:3, :3].T @ z
    up_t = level_transform(tilted, 50)[:3, :3].T @ z
    ang = np.degrees(np.arccos(np.clip(up_t @ (tilt @ up_a), -1.0, 1.0)))
    assert ang < 0.75


def test_yaw_search_puts_the_true_alignment_first(near_pair):
    found = yaw_search.search(near_pair.a, near_pair.b, coopd_params())
    assert len(found) > 10
    _, best = found[0]
    truth = near_pair.a_from_b
    # 4-DoF hypothesis on 0.3 m pixels and 2-degree steps; the tilt of the maps is left to refinement
    yaw_err = abs(np.degrees(np.angle(np.exp(1j * (np.arctan2(best[1, 0], best[0, 0])
                                                    - np.arctan2(truth[1, 0], truth[0, 0]))))))
    assert yaw_err < 3.0
    assert np.linalg.norm(best[:2, 3] - truth[:2, 3]) < 0.8


def test_a_limited_search_returns_the_first_peaks_of_the_full_one(near_pair):
    """search(limit=k) makes transforms for the k strongest peaks only: the same k, in the same order,
    as the head of the full list."""
    found = yaw_search.search(near_pair.a, near_pair.b, coopd_params())
    head = yaw_search.search(near_pair.a, near_pair.b, coopd_params(), 6)
    assert len(head) == 6
    for (s, t), (s_head, t_head) in zip(found[:6], head, strict=True):
        assert s == s_head and np.array_equal(t, t_head)
    assert [s for s, _ in found] == sorted((s for s, _ in found), reverse=True)


def test_free_pixels_next_to_a_wall_pixel_are_cleared():
    """A free pixel within one pixel (8-neighbourhood, the image's border included) of a wall pixel
    does not count: the wall's own pixel holds the free columns in front of it."""
    rng = np.random.default_rng(2)
    walls = (rng.random((40, 33)) < 0.03).astype(np.float32)
    free = (rng.random((40, 33)) < 0.5).astype(np.float32)
    near = np.zeros((42, 35), dtype=bool)
    for dx in range(3):
        for dy in range(3):
            near[dx:dx + 40, dy:dy + 33] |= walls > 0
    want = np.where(near[1:41, 1:34], 0.0, free)
    yaw_search._clear_near_walls(free, walls)
    assert np.array_equal(free, want) and free.sum() > 100


def test_fft_lengths_are_the_smallest_5_smooth_lengths_not_below_n():
    def smooth(m):
        for p in (2, 3, 5):
            while m % p == 0:
                m //= p
        return m == 1

    for n in list(range(1, 400)) + [1021, 4097, 65537]:
        got = yaw_search.fast_fft_length(n)
        assert got >= n and smooth(got) and not any(smooth(m) for m in range(n, got)), n


def test_peaks_near_a_stronger_one_in_yaw_and_landing_are_dropped():
    """Non-maximum suppression across yaws: a peak within the yaw and landing distances of a stronger
    kept one (the next yaw step of the same rotation) is a near-copy; farther in yaw or in landing,
    it is a hypothesis of its own. Yaws wrap at a full turn."""
    deg = np.radians
    yaws = deg(np.array([20.0, 22.0, 20.0, 30.0, 359.0, 1.0, 18.5]))
    landing = np.array([[0.0, 0.0], [0.5, 0.0], [3.0, 0.0], [0.0, 0.0], [5.0, 5.0], [5.0, 5.5], [0.0, 1.0]])
    keep = yaw_search.distinct_peaks(yaws, landing, deg(6.0), 1.5)
    assert keep == [0, 2, 3, 4]
    assert yaw_search.distinct_peaks(yaws, landing, deg(6.0), 1.5, limit=2) == [0, 2]
    assert yaw_search.distinct_peaks(yaws, landing, deg(1.0), 0.1) == list(range(7))


def test_the_search_hands_on_distinct_hypotheses(near_pair):
    """No two of the search's hypotheses are near-copies (within the distinct yaw and landing
    distances); without the suppression the strongest peaks include such copies on this pair."""
    params = coopd_params()
    found = yaw_search.search(near_pair.a, near_pair.b, params, params.search_candidates)
    copies = yaw_search.search(near_pair.a, near_pair.b, params.with_(search_distinct_deg=0.0),
                               params.search_candidates)

    def yaw(t):
        return np.arctan2(t[1, 0], t[0, 0])

    def near_copies(hyps):
        """Pairs within the distinct yaw whose b origins land within 0.5 m of each other (b's wall
        centre, which the search measures landing at, moves less than a metre more for such turns)."""
        limit = np.radians(params.search_distinct_deg)
        return sum(abs(np.angle(np.exp(1j * (yaw(ti) - yaw(tj))))) <= limit
                   and np.linalg.norm(ti[:2, 3] - tj[:2, 3]) < 0.5
                   for k, (_, ti) in enumerate(hyps) for _, tj in hyps[:k])

    assert len(found) == params.search_candidates
    assert near_copies(copies) > 0
    assert near_copies(found) == 0
    assert found[0][0] == copies[0][0] and np.array_equal(found[0][1], copies[0][1])
