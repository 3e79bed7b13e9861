"""The sim sensor's contact geometry: the workcell scene's forces, at the objects' live poses."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from services.control.force.kernel import mat9
from services.control.force.world import ContactWorld, Pose, carried_mass_kg
from services.world.workcell.scene import Box, Cylinder, Scene, default_scene
from tests.control.force.helpers import rot

SCENE = default_scene()
coord = st.floats(-0.05, 0.05, allow_nan=False)
radius = st.sampled_from([0.0, 0.005, 0.02])
anchors = (
    [b.center for b in SCENE.boxes]
    + [(c.base[0], c.base[1], c.base[2] + z) for c in SCENE.cylinders for z in (0.0, 0.1, 0.2)]
    + [(0.3, 0.0, 0.0), (0.6, 0.45, 0.4)]
)


@settings(max_examples=150, deadline=None)
@given(st.sampled_from(anchors), coord, coord, coord, radius)
def test_same_forces_as_the_scene(anchor: tuple, dx: float, dy: float, dz: float, r: float) -> None:
    p = np.array(anchor) + np.array([dx, dy, dz])
    world = ContactWorld.build(SCENE, r)
    np.testing.assert_allclose(world.force(*p), SCENE.contact_force(p, r), atol=1e-9)


@settings(max_examples=80, deadline=None)
@given(st.sampled_from(anchors), coord, coord, coord, st.floats(-0.2, 0.2), st.floats(-0.2, 0.2))
def test_moved_objects_as_the_moved_scene(
    anchor: tuple, dx: float, dy: float, dz: float, mx: float, my: float
) -> None:
    origins = {"block1": (0.5 + mx, -0.1 + my, 0.425), "bottle": (0.55 - my, 0.25 + mx, 0.40)}
    moved = SCENE.moved(origins)
    world = ContactWorld.build(SCENE, 0.005, {n: Pose(o) for n, o in origins.items()})
    p = np.array(anchor) + np.array([dx, dy, dz])
    np.testing.assert_allclose(world.force(*p), moved.contact_force(p, 0.005), atol=1e-9)


@settings(max_examples=80, deadline=None)
@given(coord, coord, coord, radius)
def test_a_turned_box_is_touched_where_it_lies(dx: float, dy: float, dz: float, r: float) -> None:
    # A 0.2 × 0.05 × 0.05 bar turned 90° about z is the 0.05 × 0.2 × 0.05 bar.
    bar = Box("bar", (0.0, 0.0, 0.5), (0.2, 0.05, 0.05), movable=True)
    scene = Scene(boxes=(bar,))
    turned = Scene(boxes=(replace(bar, size=(0.05, 0.2, 0.05)),))
    world = ContactWorld.build(scene, r, {"bar": Pose((0.0, 0.0, 0.5), mat9(rot("z", np.pi / 2)))})
    p = np.array([2 * dx, 4 * dy, 0.5 + dz])
    # Inside, with two faces equally near, either is right: leave such points out.
    h = np.array([0.025, 0.1, 0.025])
    faces = np.sort(np.concatenate([p - (0, 0, 0.5) + h, h - p + (0, 0, 0.5)]))
    assume(faces[0] < 0.0 or faces[1] - faces[0] > 1e-9)
    np.testing.assert_allclose(world.force(*p), turned.contact_force(p, r), atol=1e-9)


def test_a_toppled_bottle_pushes_up_from_its_side() -> None:
    bottle = Cylinder("bottle", (0.0, 0.0, 0.035), 0.035, 0.2, movable=True)
    scene = Scene(cylinders=(bottle,))
    lying = Pose((0.0, 0.0, 0.035), mat9(rot("x", -np.pi / 2)))  # axis along +y
    world = ContactWorld.build(scene, 0.005, {"bottle": lying})
    # 2 mm into its upper side, half-way along: pushed up with k · 2 mm.
    f = world.force(0.0, 0.1, 0.07 + 0.003)
    np.testing.assert_allclose(f, (0.0, 0.0, bottle.stiffness_n_per_m * 0.002), atol=1e-9)
    # Where it stood (above its old top), nothing.
    assert world.force(0.0, 0.0, 0.035 + 0.2 + 0.003) == (0.0, 0.0, 0.0)


def test_the_held_object_is_not_touched_by_the_palm() -> None:
    top = SCENE.box("block0").top_z
    p = (0.5, -0.2, top + 0.003)
    assert ContactWorld.build(SCENE, 0.005).force(*p)[2] > 0.0
    assert ContactWorld.build(SCENE, 0.005, exclude="block0").force(*p) == (0.0, 0.0, 0.0)


def test_masses_from_the_scene_description() -> None:
    block = SCENE.box("block0")
    assert carried_mass_kg(block, None, 700.0, 0.1) == pytest.approx(700.0 * 0.05**3)
    bottle = SCENE.cylinder("bottle")
    assert carried_mass_kg(bottle, 500.0, 700.0, 0.1) == pytest.approx(0.6)
    assert carried_mass_kg(bottle, None, 700.0, 0.1) == pytest.approx(0.1)
    full = np.pi * 0.035**2 * 0.2 * 1e6  # ml: a forged liquid_ml weighs no more than that
    assert carried_mass_kg(bottle, 1e12, 700.0, 0.1) == pytest.approx(0.1 + full * 1e-3)
