import numpy as np

from coopd.merging.matching import hamming_block, match
from coopd.merging.params import MergeParams


def _reference_hamming(da, db):
    x = da[None, :, :] ^ db[:, None, :]
    return np.unpackbits(x.view(np.uint8), axis=2).sum(axis=2)


def test_hamming_matches_a_bit_count_reference():
    rng = np.random.default_rng(0)
    da = rng.integers(0, 2**63, (17, 4), dtype=np.uint64)
    db = rng.integers(0, 2**63, (9, 4), dtype=np.uint64)
    assert np.array_equal(hamming_block(da, db), _reference_hamming(da, db))


def test_chunked_matching_equals_one_block_and_respects_cc_d():
    rng = np.random.default_rng(1)
    da = rng.integers(0, 2**63, (40, 4), dtype=np.uint64)
    db = da[rng.permutation(40)[:25]].copy()
    db[:5, 0] ^= np.uint64(0b111)  # three flipped bits
    small = match(da, db, MergeParams(match_chunk=4, match_max_distance=20))
    big = match(da, db, MergeParams(match_chunk=1000, match_max_distance=20))
    for x, y in zip(small, big, strict=True):
        assert np.array_equal(x, y)
    ia, ib, d = small
    assert np.all(d <= 20) and len(ia) >= 25
    assert np.all(hamming_block(da[ia], db[ib]).diagonal() == d)


def test_best_k_keeps_k_nearest_per_keypoint():
    rng = np.random.default_rng(2)
    da = rng.integers(0, 2**63, (30, 4), dtype=np.uint64)
    db = da[:10].copy()
    ia, ib, d = match(da, db, MergeParams(match_best_k=2, match_max_distance=256))
    assert len(ia) == 20
    best = {int(b): int(a) for a, b, dd in zip(ia, ib, d, strict=True) if dd == 0}
    assert best == {i: i for i in range(10)}
