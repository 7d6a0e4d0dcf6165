"""Generated worlds (gen:SEED[:key=value,...]): deterministic, flyable, inside their bounds, symmetric
when asked; the six hand-built worlds unchanged."""

from __future__ import annotations

import argparse
import hashlib
import math

import mujoco
import numpy as np
import pytest

from firmware_sim.cli import parse_args
from firmware_sim.worldgen import GenParams, parse_spec
from firmware_sim.worlds import GENERATORS, build_world, world_name

from .test_worlds import cell_of

SPECS = [f"gen:{s}" for s in range(8)] + [
    "gen:11:outdoor=1,clutter=3",
    "gen:12:symmetry=mirror",
    "gen:13:symmetry=rot180,corridors=2",
    "gen:14:outdoor=1,symmetry=rot180",
    "gen:15:size=40x12,corridors=4,rooms=20,clutter=2",
    "gen:16:size=8x8,rooms=1,corridors=0,outdoor=0,clutter=2",
]

SIX_WORLDS_MJCF_SHA1 = {
    "maze": "46e1e930bbc746b1", "small_house": "b17c3c7288bf4211", "small_warehouse": "2efc70f70b13388a",
    "bookstore": "09ca75afaa38cd6d", "hospital": "107c1595e5112fa9", "racetrack": "8871cf25bda527db",
}


def test_six_worlds_are_unchanged():
    got = {n: hashlib.sha1(build_world(n, 0).mjcf.encode()).hexdigest()[:16] for n in GENERATORS}
    assert got == SIX_WORLDS_MJCF_SHA1


@pytest.mark.parametrize("spec", SPECS[:4] + SPECS[8:])
def test_deterministic_per_seed_and_the_full_name_rebuilds_it(spec):
    a, b = build_world(spec), build_world(spec)
    assert a.mjcf == b.mjcf and a.name == b.name
    assert a.name.startswith(spec.split(":")[0] + ":" + spec.split(":")[1] + ":size=")
    assert build_world(a.name).mjcf == a.mjcf
    m = mujoco.MjModel.from_xml_string(a.mjcf)
    assert m.ngeom == len(a.shapes) > 5


def test_seeds_and_parameters_change_the_world():
    worlds = {build_world(f"gen:{s}").mjcf for s in range(6)}
    assert len(worlds) == 6
    assert build_world("gen:3:clutter=0").mjcf != build_world("gen:3:clutter=2").mjcf
    # the seed argument is used only when the name carries none
    assert build_world("gen", seed=4).mjcf == build_world("gen:4").mjcf
    assert build_world("gen:4", seed=9).mjcf == build_world("gen:4").mjcf


def test_parameters_shape_the_world():
    indoor = build_world("gen:5:outdoor=0,size=30x20,clutter=0")
    outdoor = build_world("gen:5:outdoor=1,size=30x20")
    assert any(s.name.startswith("wall_") for s in indoor.shapes)
    assert not any(s.name.startswith("wall_") for s in outdoor.shapes)
    assert all(s.name.startswith(("wall_", "floor_")) for s in indoor.shapes)
    lo, hi = indoor.bounds_min, indoor.bounds_max
    assert np.allclose(hi[:2] - lo[:2], [30.4, 20.4])
    assert build_world("gen:5:size=30x20", size=0.5).bounds_max[0] == pytest.approx(15.2)


@pytest.mark.parametrize("spec", SPECS)
def test_shapes_inside_bounds_and_routes_keep_clear_of_geometry(spec):
    w = build_world(spec)
    for s in w.shapes:
        lo, hi = s.bounds()
        assert np.all(lo >= w.bounds_min - 1e-9) and np.all(hi <= w.bounds_max + 1e-9), (spec, s)
    occ, origin = w.ground_truth(0.1)
    poses = w.start_poses(3)
    for p in poses:
        assert w.is_clear(p[0], p[1], 0.5)
    for i in range(3):
        route = w.route(i, 3)
        assert len(route) >= 4
        for a, b in zip(route[:-1], route[1:], strict=True):
            for s in np.linspace(0, 1, max(2, int(np.linalg.norm(b - a) / 0.05))):
                p = a + s * (b - a)
                assert w.is_clear(p[0], p[1], 0.3), (spec, i, p)
                assert not occ[cell_of(origin, p, 0.1)]


@pytest.mark.parametrize(("spec", "flip"), [("gen:12:symmetry=mirror", (0,)),
                                            ("gen:13:symmetry=rot180,corridors=2", (0, 1)),
                                            ("gen:14:outdoor=1,symmetry=rot180", (0, 1))])
def test_symmetric_worlds_are_symmetric(spec, flip):
    occ, _ = build_world(spec).ground_truth(0.1)
    assert np.mean(occ == np.flip(occ, axis=flip)) > 0.9999
    plain = build_world(spec.replace("symmetry=mirror", "symmetry=none").replace("symmetry=rot180",
                                                                                   "symmetry=none"))
    occ, _ = plain.ground_truth(0.1)
    assert np.mean(occ == np.flip(occ, axis=flip)) < 0.99


@pytest.mark.parametrize("bad", ["gen:x", "gen:-1", "gen:1:rooms=0", "gen:1:size=5x20", "gen:1:size=20",
                                 "gen:1:colour=red", "gen:1:outdoor=maybe", "gen:1:symmetry=spiral",
                                 "gen:1:clutter=9", "gen:1:corridors=5", "gen:1:rooms"])
def test_malformed_names_are_refused_clearly(bad):
    with pytest.raises(ValueError, match="world"):
        build_world(bad)
    with pytest.raises(argparse.ArgumentTypeError):
        world_name(bad)


def test_parse_spec_and_the_simulator_command_line():
    assert parse_spec("gen:7:rooms=6,size=30x20,outdoor=0") == (
        7, GenParams(size=(30.0, 20.0), rooms=6, outdoor=False))
    assert parse_args(["--world", "gen:7:rooms=6"]).world == "gen:7:rooms=6"
    assert parse_args(["--world", "maze"]).world == "maze"
    with pytest.raises(SystemExit):
        parse_args(["--world", "moon"])


@pytest.mark.slow
@pytest.mark.cpu_bound
@pytest.mark.parametrize("spec", ["gen:21:size=14x10,corridors=1,rooms=3,outdoor=0,clutter=1.5",
                                  "gen:22:size=16x12,outdoor=1,clutter=2"])
def test_generated_worlds_fly_their_builtin_routes_clean(spec):
    from firmware_sim.frames import quat_to_mat
    from firmware_sim.simulation import Simulation

    sim = Simulation(build_world(spec), 2, seed=3, mavlink=False, camera=None, route="builtin")
    for _ in range(400):
        sim.step(1.0)
        if all(sim.route_finished(i) for i in range(2)):
            break
    for i in range(2):
        assert sim.route_finished(i), (spec, i)
        traj = sim.trajectory(i)
        assert traj[:, 3].max() > 0.9
        tilt = [quat_to_mat(q)[2, 2] for q in traj[:, 4:8]]
        assert min(tilt) > math.cos(math.radians(25))  # no knocks against door frames, walls or objects
