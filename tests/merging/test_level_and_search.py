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
