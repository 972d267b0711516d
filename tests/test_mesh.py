"""`infer --cuboid --mesh DIR` (cuboidtrain/infer/mesh.py): each fitted box as an OBJ file in the camera's
frame whose vertices reproject onto the record's keypoints, closed boxes with outward faces; the
options it needs and the folders it refuses; and the explanation panel's 3D tile that draws the same box."""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from cuboidgen.config import PAPER_CLEAN
from cuboidtrain.cli import app
from cuboidtrain.fit.fitter import Fitter, Writers
from cuboidtrain.geometry.camera_params import describe
from cuboidtrain.infer.mesh import NOMINAL_DISTANCE, MeshWriter, camera_box, obj_text, read_obj
from cuboidtrain.fit.options import FitOptions
from shared.camera import project
from shared.errors import UsageError
from tests.conftest import build_sample

SIZE = 128


@pytest.fixture(scope="module")
def masks(tmp_path_factory) -> dict[str, str]:
    """A clean generated box and twobox mask, as PNGs."""
    folder = tmp_path_factory.mktemp("mesh-masks")
    paths = {}
    for shape, seed in (("box", 1), ("twobox", 1)):
        sample = build_sample(seed, shape, size=SIZE, scene=PAPER_CLEAN)
        paths[shape] = str(folder / f"{shape}-{seed}.png")
        assert cv2.imwrite(paths[shape], sample.clean.astype(np.uint8) * 255)
    return paths


@pytest.fixture(scope="module")
def fits(masks):
    """Each mask's --cuboid fit as its own shape class (the shipped models)."""
    return {shape: Fitter.from_shipped(FitOptions(shape=shape, device="cpu", cuboid=True)).fit(path)
            for shape, path in masks.items()}


def signed_volume(vertices: np.ndarray, faces) -> float:
    """The volume a closed mesh encloses, positive when its faces wind counter-clockwise seen from outside."""
    total = 0.0
    for face in faces:
        for a, b in zip(face[1:-1], face[2:]):  # a fan of triangles
            total += np.linalg.det(np.stack([vertices[face[0]], vertices[a], vertices[b]])) / 6
    return total


@pytest.mark.parametrize("shape", ["box", "twobox"])
def test_the_obj_file_reprojects_onto_the_records_keypoints(tmp_path, masks, fits, shape):
    fit = fits[shape]
    writer = MeshWriter(tmp_path / "out")
    assert writer(0, masks[shape], fit) == ()
    assert writer.written == [tmp_path / "out" / f"{shape}-1.obj"]
    vertices, _ = read_obj(writer.written[0])
    assert vertices.shape == (len(fit.keypoints), 3) and (vertices[:, 2] > 0).all()  # in front of the camera
    # the fitted camera (the record's focal length and principal point) puts vertex k on keypoint k
    cuboid, intrinsics = fit.cuboid.fit.camera.pinhole()
    record = fit.record()["cuboid"]
    assert math.isclose(intrinsics.focal, record["focal_px"])
    assert np.allclose(intrinsics.principal, record["principal_px"])
    assert np.abs(project(vertices, intrinsics) - np.asarray(fit.keypoints)).max() < 1e-6
    # and the vertices are shared.camera's cuboid, posed in its camera, in the record's (viewer) names
    assert np.allclose(vertices, cuboid.named_corners(fit.cuboid.fit.camera.shape).camera, atol=1e-9)
    # units: the (taller) part's height is 1
    heights = [np.linalg.norm(vertices[part[0]] - vertices[part[1]]) for part in fit.cuboid.fit.camera.shape.parts]
    assert math.isclose(max(heights), 1.0)
    text = writer.written[0].read_text()
    assert f"focal_px {intrinsics.focal!r}" in text and "x right, y down, z forward" in text


@pytest.mark.parametrize("shape, parts", [("box", ["box"]), ("twobox", ["right", "left"])])
def test_each_part_is_a_closed_box_of_six_outward_quads(tmp_path, masks, fits, shape, parts):
    writer = MeshWriter(tmp_path)
    writer(0, masks[shape], fits[shape])
    vertices, objects = read_obj(writer.written[0])
    assert list(objects) == parts
    for name, faces in objects.items():
        assert len(faces) == 6 and all(len(f) == 4 for f in faces)
        assert len({i for f in faces for i in f}) == 8
        # closed and consistently wound: every edge once each way
        directed = [(f[k], f[(k + 1) % 4]) for f in faces for k in range(4)]
        assert len(set(directed)) == 24 and all((b, a) in directed for a, b in directed)
        for face in faces:  # planar quads
            a, b, c, d = vertices[list(face)]
            assert abs(np.dot(np.cross(b - a, c - a), d - a)) < 1e-9
        # outward: the enclosed volume is positive, and the box's own (its three edge lengths' product)
        part = fits[shape].cuboid.fit.camera.shape.parts[parts.index(name)]
        edges = [np.linalg.norm(vertices[part[0]] - vertices[part[bit]]) for bit in (1, 2, 4)]
        assert signed_volume(vertices, faces) == pytest.approx(np.prod(edges), rel=1e-9)


def test_a_weak_perspective_fit_is_placed_at_a_nominal_distance(fits):
    fit = fits["box"].cuboid.fit
    vector = fit.camera.vector.copy()
    vector[8] = 0.0  # k = 0: the camera infinitely far
    weak = describe(replace(fit.camera, vector=vector), fit.residual_px, fit.iou)
    assert weak.focal_px == math.inf
    box = camera_box(weak)
    assert box.nominal and np.allclose(np.linalg.norm(box.corners.mean(axis=0)), NOMINAL_DISTANCE, rtol=0.01)
    span = np.ptp(weak.keypoints, axis=0).max()
    depth = np.ptp(box.corners[:, 2])  # in box heights
    assert np.abs(box.project() - weak.keypoints).max() < span * depth / NOMINAL_DISTANCE
    assert "weak perspective" in obj_text(box)


def test_files_are_named_like_the_explanation_panels(tmp_path, masks, fits):
    folder = tmp_path / "out"
    (tmp_path / "a").mkdir(), (tmp_path / "b").mkdir()
    inputs = [str(tmp_path / "a" / "x.png"), str(tmp_path / "b" / "x.png"), str(tmp_path / "y.png")]
    writer = MeshWriter(folder, inputs)
    for index in (2, 1, 0):  # in any order, as a pool's workers finish
        writer(index, inputs[index], fits["box"])
    writer(0, inputs[0], replace(fits["box"], component=1))
    assert sorted(p.name for p in folder.iterdir()) == ["x-1.obj", "x-input1.obj", "x.obj", "y.obj"]


def test_a_fit_without_a_cuboid_or_a_failed_write_is_a_warning(tmp_path, masks, fits, monkeypatch):
    writer = MeshWriter(tmp_path)
    no_cuboid = writer(0, "m.png", replace(fits["box"], cuboid=None))
    assert no_cuboid == ("no mesh: the fit has no cuboid (fit with --cuboid)",)

    def full_disk(path):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("cuboidtrain.infer.mesh.atomic_path", full_disk)
    assert writer(0, "m.png", fits["box"]) == ("no mesh: [Errno 28] No space left on device",)
    assert writer.written == []


def test_the_writers_run_in_turn_and_return_every_warning(tmp_path, fits):
    calls = []
    both = Writers.of(lambda i, p, f: calls.append("a") or ("one",), None, lambda i, p, f: calls.append("b") or ())
    assert both(0, "m.png", fits["box"]) == ("one",) and calls == ["a", "b"]
    assert Writers.of(None, None) is None


def test_a_file_where_the_folder_should_be_is_refused(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(UsageError, match=r"--mesh .*file: not a folder"):
        MeshWriter(tmp_path / "file")


@pytest.mark.parametrize("extra, message", [
    (["--networks-only"], "--mesh {out} with --networks-only: expected the cuboid fit"),
    (["--cuboid", "--cluster", "local"], "--mesh with --cluster local: expected no --cluster"),
])
def test_bad_mesh_options_fail_in_one_line_before_any_fit(tmp_path, masks, extra, message):
    out = tmp_path / "meshes"
    result = CliRunner().invoke(app, ["infer", masks["box"], "--mesh", str(out), *extra])
    assert result.exit_code == 2, result.output
    assert message.format(out=out) in result.output and len(result.output.strip().splitlines()) == 1
    assert not out.exists()


@pytest.mark.parametrize("target", ["file", "missing/deeper/meshes"])
def test_the_mesh_folder_is_checked_like_the_explanation_folder(tmp_path, masks, target):
    (tmp_path / "file").write_text("")
    result = CliRunner().invoke(app, ["infer", masks["box"], "--cuboid", "--mesh", str(tmp_path / target),
                                      "--json", str(tmp_path / "out.json")])
    if target == "file":
        assert result.exit_code == 2 and "--mesh" in result.output and "not a folder" in result.output
        assert not (tmp_path / "out.json").exists()
    else:  # a new folder, with its missing parents, is made
        assert result.exit_code == 0, result.output
        assert (tmp_path / target / "box-1.obj").is_file()


@pytest.mark.parametrize("workers", [1, 2])
def test_infer_writes_one_mesh_per_input_in_this_process_or_a_pool(tmp_path, masks, workers):
    out = tmp_path / "meshes"
    result = CliRunner().invoke(app, ["infer", masks["box"], masks["twobox"], "--cuboid", "--device", "cpu",
                                      "--mesh", str(out), "--workers", str(workers),
                                      "--json", str(tmp_path / "out.json")])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == ["box-1.obj", "twobox-1.obj"]
    assert f"2 meshes in {out}" in " ".join(result.output.split())  # rich wraps long lines

