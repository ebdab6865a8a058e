"""Geometry of the truncated icosahedron (perception.icosahedron, paper section 3.1)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from perception.icosahedron import PHI, TruncatedIcosahedron, icosahedron_vertices


@pytest.fixture(scope="module")
def ico() -> TruncatedIcosahedron:
    return TruncatedIcosahedron(4.0)


def test_counts(ico):
    assert ico.vertices.shape == (60, 3)
    assert ico.edges.shape == (90, 2)
    assert len(ico.faces) == 32
    assert ico.normals.shape == (32, 3)
    assert ico.offsets.shape == (32,)
    assert ico.centres.shape == (32, 3)
    assert ico.is_pentagon.dtype == bool
    assert ico.is_pentagon.sum() == 12
    assert (~ico.is_pentagon).sum() == 20
    assert [len(f) for f in ico.faces] == [5] * 12 + [6] * 20


def test_vertices_on_circumsphere(ico):
    np.testing.assert_allclose(np.linalg.norm(ico.vertices, axis=1), 4.0, rtol=1e-12)
    # distinct vertices
    d = np.linalg.norm(ico.vertices[:, None] - ico.vertices[None], axis=-1)
    assert d[~np.eye(60, dtype=bool)].min() > 1.0


def test_ninety_equal_edges(ico):
    d = np.linalg.norm(ico.vertices[:, None] - ico.vertices[None], axis=-1)
    iu = np.triu_indices(60, k=1)
    pair_d = d[iu]
    shortest = pair_d.min()
    assert np.count_nonzero(np.isclose(pair_d, shortest, rtol=1e-9)) == 90
    # the stored edges are exactly those pairs
    stored = np.linalg.norm(ico.vertices[ico.edges[:, 0]] - ico.vertices[ico.edges[:, 1]], axis=1)
    np.testing.assert_allclose(stored, shortest, rtol=1e-9)
    assert ico.edge_length == pytest.approx(shortest)
    # every vertex has degree 3 (one pentagon, two hexagons meet there)
    assert np.all(np.bincount(ico.edges.ravel(), minlength=60) == 3)


def test_every_face_plane_holds_5_or_6_vertices(ico):
    proj = ico.vertices @ ico.normals.T  # (60, 32)
    for i in range(32):
        on_plane = np.flatnonzero(np.isclose(proj[:, i], ico.offsets[i], atol=1e-9))
        expected = 5 if ico.is_pentagon[i] else 6
        assert len(on_plane) == expected
        assert sorted(on_plane.tolist()) == sorted(ico.faces[i])
    # each vertex lies on exactly 3 face planes (one pentagon, two hexagons)
    on = np.isclose(proj, ico.offsets[None, :], atol=1e-9)
    assert np.all(on.sum(axis=1) == 3)
    assert np.all(on[:, ico.is_pentagon].sum(axis=1) == 1)


def test_offsets_and_centres(ico):
    np.testing.assert_allclose(ico.offsets[ico.is_pentagon], 3.757, atol=5e-4)
    np.testing.assert_allclose(ico.offsets[~ico.is_pentagon], 3.660, atol=5e-4)
    np.testing.assert_allclose(np.linalg.norm(ico.normals, axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(ico.centres, ico.offsets[:, None] * ico.normals, rtol=1e-12)
    # the face centre is the centroid of the face's vertices
    for i, f in enumerate(ico.faces):
        np.testing.assert_allclose(ico.vertices[f].mean(axis=0), ico.centres[i], atol=1e-12)
    assert ico.inradius == pytest.approx(ico.offsets.min())
    np.testing.assert_array_equal(ico.normals_t, ico.normals.T)
    np.testing.assert_array_equal(ico.centres_t, ico.centres.T)


def test_normals_are_icosahedron_and_dodecahedron_directions(ico):
    icv = icosahedron_vertices()
    icv = icv / np.linalg.norm(icv, axis=1, keepdims=True)
    np.testing.assert_allclose(ico.normals[:12], icv, atol=1e-12)
    dodeca = [np.array(s) for s in itertools.product((1.0, -1.0), repeat=3)]
    for a, b in itertools.product((1.0, -1.0), repeat=2):
        base = (0.0, a * PHI, b / PHI)
        dodeca += [np.array(base), np.array(base[2:] + base[:2]), np.array(base[1:] + base[:1])]
    dodeca = np.array(dodeca)
    dodeca /= np.linalg.norm(dodeca, axis=1, keepdims=True)
    assert len(dodeca) == 20
    # same set of directions (order is the solid's own)
    cos = ico.normals[12:] @ dodeca.T
    assert np.all(np.isclose(cos.max(axis=1), 1.0))
    assert np.all(np.isclose(cos.max(axis=0), 1.0))


def test_all_vertices_inside_or_on_all_planes(ico):
    proj = ico.vertices @ ico.normals.T
    assert np.all(proj <= ico.offsets[None, :] + 1e-9)
    assert np.all(ico.contains(ico.vertices * (1 - 1e-9)))
    assert not np.any(ico.contains(ico.vertices * 1.001))


def test_faces_ordered_ccw_from_outside(ico):
    for i, f in enumerate(ico.faces):
        v = ico.vertices[f]
        n = len(f)
        for k in range(n):
            a, b, c = v[k], v[(k + 1) % n], v[(k + 2) % n]
            assert np.linalg.norm(b - a) == pytest.approx(ico.edge_length)
            assert np.dot(np.cross(b - a, c - b), ico.normals[i]) > 0


def test_scales_with_radius():
    small = TruncatedIcosahedron(2.0)
    big = TruncatedIcosahedron(4.0)
    np.testing.assert_allclose(small.vertices * 2.0, big.vertices, rtol=1e-12)
    np.testing.assert_allclose(small.offsets * 2.0, big.offsets, rtol=1e-12)
    assert small.faces == big.faces


def test_mirror_symmetric_left_right(ico):
    mirrored = ico.normals * np.array([1.0, -1.0, 1.0])
    assert np.all(np.isclose((mirrored @ ico.normals.T).max(axis=1), 1.0))


def test_arrays_read_only(ico):
    with pytest.raises(ValueError):
        ico.normals[0, 0] = 1.0


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_radius(bad):
    with pytest.raises(ValueError):
        TruncatedIcosahedron(bad)
