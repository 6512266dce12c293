"""Building meshes from roof faces: closed, outward, and of the hand-computed volume."""

import numpy as np
import open3d as o3d
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from data_samples.roofs import ROOF_TYPES, Wing, wing_roof_faces
from modeling.shared.roof_envelope import GRID, _wall_pieces, building_mesh


def _o3d(m):
    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(m.vertices), o3d.utility.Vector3iVector(m.triangles)
    )


def _closed_volume(m) -> float:
    om = _o3d(m)
    assert om.is_watertight(), "mesh is not watertight"
    assert om.is_orientable()
    # signed volume from the divergence theorem: positive iff normals point outwards
    v = m.vertices[m.triangles]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def test_flat_box_volume():
    m = building_mesh(wing_roof_faces(Wing(3, -2, 5, 2, 0.4), "flat", 3.0), 0.0)
    # corners of a rotated box are snapped to the 0.1 mm grid: 1e-4 relative at most
    assert _closed_volume(m) == pytest.approx(10 * 4 * 3, rel=1e-4)
    assert len(m.triangles) == 12


def test_gable_prism_volume():
    a, b, eave, bottom, pitch = 8.0, 5.0, 6.0, -1.0, 35.0
    m = building_mesh(
        wing_roof_faces(Wing(10, 5, a, b, 0.3), "gable", eave, pitch_deg=pitch), bottom
    )
    rise = b * np.tan(np.radians(pitch))
    expected = (2 * a) * (2 * b) * (eave - bottom) + (2 * a) * b * rise
    assert _closed_volume(m) == pytest.approx(expected, rel=1e-5)
    assert m.vertices[:, 2].max() == pytest.approx(eave + rise, abs=1e-4)


def test_pyramid_volume():
    a = b = 4.0
    m = building_mesh(wing_roof_faces(Wing(0, 0, a, b, 0.0), "pyramid", 5.0, pitch_deg=45), 0.0)
    expected = (2 * a) * (2 * b) * 5.0 + (2 * a) * (2 * b) * 4.0 / 3.0
    assert _closed_volume(m) == pytest.approx(expected, rel=1e-5)


def test_stepped_levels_volume():
    base = Wing(0, 0, 10, 6, 0.0)
    tiers = [(Wing(1, 0, 6, 4, 0.0), 12.0), (Wing(2, 0, 3, 2, 0.0), 20.0)]
    m = building_mesh(wing_roof_faces(base, "multi-level", 6.0, tiers=tiers), 0.0)
    expected = 20 * 12 * 6 + 12 * 8 * 6 + 6 * 4 * 8
    assert _closed_volume(m) == pytest.approx(expected, rel=1e-5)


def test_cross_gable_L_has_one_closed_surface():
    a = wing_roof_faces(Wing(0, 0, 10, 4, 0.0), "gable", 6.0)
    b = wing_roof_faces(Wing(6, 8, 8, 4, np.pi / 2), "gable", 6.0)
    m = building_mesh(a + b, -1.0)
    vol = _closed_volume(m)
    one = _closed_volume(building_mesh(a, -1.0))
    two = _closed_volume(building_mesh(b, -1.0))
    # the overlap is counted once: less than the sum, more than either
    assert max(one, two) < vol < one + two


def test_courtyard_has_a_hole():
    ws = [
        Wing(0, -10, 14, 4, 0),
        Wing(0, 10, 14, 4, 0),
        Wing(-10, 0, 14, 4, np.pi / 2),
        Wing(10, 0, 14, 4, np.pi / 2),
    ]
    faces = sum((wing_roof_faces(w, "flat", 9.0) for w in ws), [])
    m = building_mesh(faces, 0.0)
    assert _closed_volume(m) == pytest.approx((28 * 28 - 12 * 12) * 9.0, rel=1e-5)


@settings(max_examples=40, deadline=None)
@given(
    roof=st.sampled_from(ROOF_TYPES),
    a=st.floats(3.0, 20.0),
    ratio=st.floats(0.3, 1.0),
    angle=st.floats(-np.pi, np.pi),
    eave=st.floats(3.0, 30.0),
    pitch=st.floats(15.0, 50.0),
)
def test_every_roof_type_is_closed_and_above_the_eave(roof, a, ratio, angle, eave, pitch):
    b = a * ratio
    w = Wing(1.0, 2.0, a, b, angle)
    tiers = [(Wing(1.0, 2.0, a * 0.6, b * 0.6, angle), eave + 4.0)] if roof == "multi-level" else ()
    m = building_mesh(wing_roof_faces(w, roof, eave, pitch_deg=pitch, tiers=tiers), 0.0)
    vol = _closed_volume(m)
    assert vol >= (2 * a) * (2 * b) * eave * (1 - 1e-4)
    roof_z = m.vertices[m.triangles[m.part == 0]][..., 2]
    assert roof_z.min() >= eave - 1e-3


def test_a_crossing_within_the_grid_of_an_end_is_that_end():
    """Two sides of an edge that cross a hair from its end (closer than the snapping
    grid) make no wall: a sliver there would have no partner in the noded cells."""
    p0, p1 = np.array([0.0, 0.0]), np.array([1.0, 0.0])
    assert _wall_pieces(p0, p1, 5.0 + GRID / 10, 4.0, 5.0, 5.0) == []
    assert len(_wall_pieces(p0, p1, 6.0, 4.0, 5.0, 5.0)) == 1  # a real crossing: half a wall
