"""The pose-prior evaluation's parts: shape symmetry classes, the synthetic query's true camera, and the
rotation error modulo a symmetry axis (the run itself: docs/results.md, section 8; the evaluation end to
end on synth queries: tests/test_handoff.py)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.evaluate import pose_prior
from pipeline.mesh import frames


@pytest.mark.parametrize(
    ("shape", "want"),
    [("cylinder", "radial"), ("sphere", "spherical"), ("box", "none"), ("blade", "none"), ("cone", "radial")],
)
def test_symmetry_class_from_shape(shape, want):
    import trimesh

    mesh = {
        "cylinder": lambda: trimesh.creation.cylinder(radius=0.03, height=0.1, sections=64),
        "sphere": lambda: trimesh.creation.icosphere(subdivisions=4, radius=0.04),
        "box": lambda: trimesh.creation.box((0.06, 0.1, 0.2)),
        "blade": lambda: trimesh.creation.box((0.002, 0.02, 0.2)),  # a knife: thin, long, not a rod
        "cone": lambda: trimesh.creation.cone(radius=0.05, height=0.08, sections=64),
    }[shape]()
    rot = trimesh.transformations.random_rotation_matrix(np.random.default_rng(3).random(3))
    mesh.apply_transform(rot)
    mesh.apply_translation((0.3, -0.1, 0.05))
    sym, axis = pose_prior.symmetry_class(mesh)
    assert sym == want
    if want == "radial":  # the axis found is the shape's own (z before the rotation)
        assert abs(float(np.dot(axis, rot[:3, 2]))) > 0.999


def test_true_camera_is_synths_camera():
    """The camera synth renders a query from: look-at on the (azimuth, elevation) ray, then rolled."""
    pose = pose_prior.true_camera_gl(30.0, 20.0, 0.0)
    rolled = pose_prior.true_camera_gl(30.0, 20.0, 12.0)
    az, el = np.radians(30.0), np.radians(20.0)
    d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    assert np.allclose(-pose[:3, 2], -d)  # looks at the origin along -direction (OpenGL: -z forward)
    assert np.allclose(rolled[:3, 2], pose[:3, 2])  # a roll keeps the optical axis
    assert frames.rotation_angle_deg(pose[:3, :3], rolled[:3, :3]) == pytest.approx(12.0)


def test_rotation_error_modulo_an_axis():
    axis = np.array([0.0, 0.0, 1.0])
    r_true = np.eye(3)
    spun = r_true @ pose_prior._axis_rotation(axis, 100.0)  # turned about its own symmetry axis
    err, mod = pose_prior.rotation_errors(spun, r_true, "radial", axis)
    assert err == pytest.approx(100.0) and mod == pytest.approx(0.0, abs=0.6)
    tilted = pose_prior._axis_rotation(np.array([1.0, 0.0, 0.0]), 20.0) @ spun
    err, mod = pose_prior.rotation_errors(tilted, r_true, "radial", axis)
    assert mod == pytest.approx(20.0, abs=0.6) and err > 90.0
    assert pose_prior.rotation_errors(spun, r_true, "spherical", None) == (pytest.approx(100.0), 0.0)
    assert pose_prior.rotation_errors(spun, r_true, "none", None) == (
        pytest.approx(100.0),
        pytest.approx(100.0),
    )


def test_table_counts_within_threshold():
    rows = [
        {"query_id": "a", "symmetry": "none", "top1": True, "error_deg": 10.0, "error_sym_deg": 10.0},
        {"query_id": "b", "symmetry": "radial", "top1": False, "error_deg": 120.0, "error_sym_deg": 20.0},
        {"query_id": "c", "symmetry": "none", "top1": True, "error_deg": None, "error_sym_deg": None},
    ]
    text = pose_prior.table(rows, {"a": 5.0, "b": 25.0, "c": 30.0})
    assert (
        "| all | 3 | 2 | 65.0 [10.0, 120.0] | 1/2 (50% [0, 100]) | 15.0 [10.0, 20.0] | 2/2 (100% [100, 100]) |"
        in text
    )
    assert "| symmetry: radial | 1 | 1 | 120.0 [120.0, 120.0] | 0/1 (0% [0, 0]) | 20.0 [20.0, 20.0] |" in text


def test_cli_refuses_a_file_without_synthetic_cameras(tmp_path, capsys):
    (tmp_path / "q.jsonl").write_text('{"image": "x.png", "prompt": "a can", "expected": ["m"]}\n')
    (tmp_path / "x.png").write_bytes(b"")
    assert pose_prior.main(["--store", str(tmp_path), "--queries", str(tmp_path / "q.jsonl")]) == 2
    assert "no synthetic queries with camera metadata" in capsys.readouterr().err
