"""Maps of different resolutions merge: B is resampled to A's resolution at the merging entry points."""

import numpy as np
import pytest

from coopd.geometry import rotation_angle_deg
from coopd.merging.offline import merge_grids
from coopd.merging.pair import merge_pair
from firmware_sim.exploration import occupied_points
from firmware_sim.mergeset import displacement, world_pairs
from firmware_sim.worlds import build_world


@pytest.fixture(scope="module")
def pairs():
    world = build_world("gen:2:size=20x15,outdoor=0")
    return {p.variant: p for p in world_pairs(world, 1, 4.0, ["res0.2", "res0.05"])}


@pytest.mark.parametrize("variant", ["res0.2", "res0.05"])
def test_merge_pair_of_mixed_resolutions_finds_the_truth(pairs, variant):
    p = pairs[variant]
    assert p.b.resolution != p.a.resolution
    r = merge_pair(p.a, p.b)
    mean, _ = displacement(r.transform, p.a_from_b, occupied_points(p.b))
    rot = rotation_angle_deg(r.transform[:3, :3].T @ p.a_from_b[:3, :3])
    print(f"{variant}: accepted {r.accepted}, {rot:.2f} deg, mean displacement {mean:.3f} m")
    assert r.accepted and rot < 2.0 and mean < 0.2, r.reason


def test_offline_merge_fuses_a_coarser_map_into_the_reference_resolution(pairs):
    p = pairs["res0.2"]
    merged, report = merge_grids([p.a, p.b])
    assert merged.resolution == p.a.resolution
    assert report["maps"][0]["accepted"], report
    assert (merged.cells >= 0).sum() > (p.a.cells >= 0).sum()
    t = np.array(report["maps"][0]["transform"])
    assert rotation_angle_deg(t[:3, :3].T @ p.a_from_b[:3, :3]) < 2.0


def test_comparable_coarsens_a_finer_map_and_keeps_a_coarser_one(pairs):
    from coopd.merging.pair import comparable

    fine, coarse = pairs["res0.05"].b, pairs["res0.2"].b
    assert comparable(fine, 0.1).resolution == 0.1
    assert comparable(coarse, 0.1) is coarse
    assert comparable(pairs["base"].b, 0.1) is pairs["base"].b
