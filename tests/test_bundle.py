"""The ``.narf`` bundle: an exact save/load round trip, atomic writes, and clear refusals of files it cannot use."""

from __future__ import annotations

import dataclasses
import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

pytest_plugins = ("conftest_model",)

from narf_core.bundle import (  # noqa: E402
    FORMAT,
    FORMAT_VERSION,
    BundleError,
    load_bundle,
    read_metadata,
    save_bundle,
    tensors_digest,
)
from narf_core.data.dataset import Dataset  # noqa: E402


def header(path: Path) -> dict:
    """The safetensors JSON header of ``path``."""
    raw = path.read_bytes()
    (length,) = struct.unpack("<Q", raw[:8])
    return json.loads(raw[8 : 8 + length])


def rewrite_metadata(src: Path, dst: Path, change) -> Path:
    """``src`` with its ``"narf"`` metadata replaced by ``change(meta)`` (tensor bytes untouched)."""
    raw = src.read_bytes()
    (length,) = struct.unpack("<Q", raw[:8])
    head = json.loads(raw[8 : 8 + length])
    head["__metadata__"]["narf"] = json.dumps(change(json.loads(head["__metadata__"]["narf"])))
    text = json.dumps(head).encode()
    text += b" " * (-len(text) % 8)
    dst.write_bytes(struct.pack("<Q", len(text)) + text + raw[8 + length :])
    return dst


def unchecked_metadata(path: Path) -> dict:
    """``path``'s safetensors metadata without the tensors' checksum, as bundles were saved before
    checksums existed: tests that change tensors then reach the structural checks."""
    metadata = header(path)["__metadata__"]
    narf = json.loads(metadata["narf"])
    narf.pop("checksum", None)
    return {**metadata, "narf": json.dumps(narf)}


def first_test_view(dataset_root: Path):
    dataset = Dataset.open(dataset_root)
    frame = dataset.frames("test")[0]
    return torch.as_tensor(frame.T_cam_obj, dtype=torch.float32), frame.joints, dataset.camera


def assert_refused(path: Path, *reason: str) -> None:
    with pytest.raises(BundleError) as info:
        load_bundle(path)
    message = str(info.value)
    assert str(path) in message
    for words in reason:
        assert words in message, message
    assert "\n" not in message


# ---------------------------------------------------------------------------------------------
# Round trip


@pytest.mark.slow
def test_round_trip_keeps_weights_grids_points_and_renders_bit_identical(tiny_bundle, tiny_dataset, tmp_path):
    model = load_bundle(tiny_bundle)
    copy = load_bundle(save_bundle(tmp_path / "copy.narf", model))

    for a, b in [(model.field, copy.field), *zip(model.part_fields, copy.part_fields)]:
        sa, sb = a.state_dict(), b.state_dict()
        assert sa.keys() == sb.keys() and len(sa) > 0
        assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert torch.equal(model.grid.occupancy, copy.grid.occupancy) and torch.equal(model.grid.aabb, copy.grid.aabb)
    ranges = (model.grid.theta_range, copy.grid.theta_range)
    assert ranges[0] is None and ranges[1] is None or torch.equal(*ranges)  # the configuration bins, if any
    assert all(torch.equal(a.occupancy, b.occupancy) for a, b in zip(model.part_grids, copy.part_grids))
    assert model.sample_points.keys() == copy.sample_points.keys() == {"lower_half", "upper_half"}
    assert all(np.array_equal(model.sample_points[k], copy.sample_points[k]) for k in model.sample_points)
    assert model.dense_points.keys() == copy.dense_points.keys() == {"lower_half", "upper_half"}  # kept at training
    assert all(np.array_equal(model.dense_points[k], copy.dense_points[k]) for k in model.dense_points)
    assert copy.step == model.step and copy.diameter == model.diameter

    T, joints, camera = first_test_view(tiny_dataset)
    for mode in ("narf", "parts"):
        theta = model.joint_vector(joints)
        a = model.render(T, theta, camera, outputs=("rgb", "depth", "opacity"), mode=mode)
        b = copy.render(T, copy.joint_vector(joints), camera, outputs=("rgb", "depth", "opacity"), mode=mode)
        assert all(torch.equal(a[k], b[k]) for k in ("rgb", "depth", "opacity"))
        assert float(a["opacity"].max()) > 0.5  # a real image, not an empty one compared with itself


@pytest.mark.slow
def test_round_trip_keeps_metadata_kinematics_and_provenance(tiny_bundle, tiny_dataset, tmp_path):
    model = load_bundle(tiny_bundle)
    path = save_bundle(tmp_path / "copy.narf", model)
    meta = read_metadata(path)
    copy = load_bundle(path)

    assert meta["format"] == FORMAT and meta["version"] == FORMAT_VERSION
    assert meta["name"] == "longnose" and copy.name == "longnose"  # the name is the file's stem at training
    assert copy.links == model.links == ["lower_half", "upper_half"]
    assert copy.joints == model.joints and [j.name for j in copy.joints] == ["pivot"]
    pivot = copy.joints[0]
    assert pivot.type == "revolute" and pivot.lower == 0.0 and pivot.upper == pytest.approx(0.6)
    assert torch.equal(copy.lower, model.lower) and torch.equal(copy.upper, model.upper)
    assert meta["urdf"] == model.kinematics.urdf_text and "<robot" in meta["urdf"]
    assert torch.equal(copy.aabb, model.aabb)
    provenance = meta["provenance"]
    assert provenance == model.metadata["provenance"]
    assert provenance["dataset"] == str(tiny_dataset) and len(provenance["dataset_hash"]) == 16
    assert provenance["config"]["part_steps"] == 30 and provenance["narf_version"]
    assert set(provenance["timings_s"]) == {"part0_s", "part1_s", "distill_s"}
    described = copy.describe()
    assert described["modes"] == ["narf", "parts"] and described["joints"][0]["name"] == "pivot"
    json.dumps(described)  # JSON-able as documented


@pytest.mark.slow
def test_forward_kinematics_of_a_loaded_bundle_need_no_dataset(tiny_bundle):
    model = load_bundle(tiny_bundle)
    lo, hi = model.kinematics.part_poses(model.lower.double()), model.kinematics.part_poses(model.upper.double())
    assert lo.shape == (2, 4, 4)
    moved = [not torch.allclose(a, b) for a, b in zip(lo, hi)]
    assert sum(moved) == 1  # the pivot moves one part relative to the other, which stays put


@pytest.mark.slow
def test_save_is_atomic_and_leaves_no_temporary_file(tiny_model, tmp_path):
    path = save_bundle(tmp_path / "sub" / "m.narf", tiny_model)  # creates the folder
    assert sorted(p.name for p in path.parent.iterdir()) == ["m.narf"]
    before = path.read_bytes()
    save_bundle(path, tiny_model)  # overwrite in place
    assert sorted(p.name for p in path.parent.iterdir()) == ["m.narf"] and path.read_bytes() == before


@pytest.mark.slow
def test_a_failed_save_keeps_the_old_file_and_leaves_no_temporary_file(tiny_model, tmp_path, monkeypatch):
    path = save_bundle(tmp_path / "m.narf", tiny_model)
    before = path.read_bytes()

    def fail_halfway(tensors, filename, metadata=None):
        Path(filename).write_bytes(b"partial")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("narf_core.bundle.save_file", fail_halfway)
    with pytest.raises(OSError, match="No space"):
        save_bundle(path, tiny_model)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["m.narf"]


# ---------------------------------------------------------------------------------------------
# Refusals: BundleError naming the file and the reason


def test_missing_file_is_refused(tmp_path):
    assert_refused(tmp_path / "nope.narf", "no such model file")


def test_a_folder_is_refused(tmp_path):
    (tmp_path / "m.narf").mkdir()
    assert_refused(tmp_path / "m.narf", "is a folder")


def test_empty_file_is_refused(tmp_path):
    path = tmp_path / "empty.narf"
    path.write_bytes(b"")
    assert_refused(path, "not a NARF model bundle", "empty")


def test_random_bytes_are_refused(tmp_path):
    path = tmp_path / "noise.narf"
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    assert_refused(path, "not a NARF model bundle", "no safetensors header")


def test_a_header_that_is_not_json_is_refused(tmp_path):
    path = tmp_path / "text.narf"
    path.write_bytes(struct.pack("<Q", 16) + b"this is no json!")
    assert_refused(path, "not a NARF model bundle")


def test_a_foreign_safetensors_file_is_refused(tmp_path):
    path = tmp_path / "foreign.narf"
    save_file({"weight": torch.zeros(3)}, str(path), metadata={"framework": "something else"})
    assert_refused(path, "not a NARF model bundle", "without 'narf' metadata")
    plain = tmp_path / "plain.narf"
    save_file({"weight": torch.zeros(3)}, str(plain))  # no metadata at all
    assert_refused(plain, "not a NARF model bundle", "without 'narf' metadata")


@pytest.mark.parametrize(("narf", "words"), [("{oops", "not JSON"), ("[1, 2]", "format [1, 2]"), ("7", "format 7")])
def test_narf_metadata_that_is_no_json_object_is_refused(tmp_path, narf, words):
    path = tmp_path / "odd.narf"
    save_file({"weight": torch.zeros(3)}, str(path), metadata={"narf": narf})
    assert_refused(path, "not a NARF model bundle", words)


@pytest.mark.slow
def test_another_format_name_is_refused(tiny_bundle, tmp_path):
    path = rewrite_metadata(tiny_bundle, tmp_path / "other.narf", lambda m: {**m, "format": "other-bundle"})
    assert_refused(path, "not a NARF model bundle", "other-bundle")


@pytest.mark.slow
@pytest.mark.parametrize("version", [FORMAT_VERSION + 1, 0, "1", None])
def test_another_format_version_is_refused(tiny_bundle, tmp_path, version):
    path = rewrite_metadata(tiny_bundle, tmp_path / "v.narf", lambda m: {**m, "version": version})
    assert_refused(path, "format version", repr(version), f"reads {FORMAT_VERSION}")


@pytest.mark.slow
def test_the_rewriting_helper_keeps_a_valid_bundle(tiny_bundle, tmp_path):
    """The refusals above come from the changed field, not from the way the file was rewritten."""
    path = rewrite_metadata(tiny_bundle, tmp_path / "same.narf", lambda m: m)
    assert header(path).keys() == header(tiny_bundle).keys()
    assert load_bundle(path).name == "longnose"


@pytest.mark.slow
@pytest.mark.parametrize("keep", [0.5, 0.999])
def test_a_truncated_bundle_is_refused(tiny_bundle, tmp_path, keep):
    raw = tiny_bundle.read_bytes()
    path = tmp_path / "cut.narf"
    path.write_bytes(raw[: int(len(raw) * keep)])
    assert_refused(path, "corrupt model bundle")


@pytest.mark.slow
def test_a_truncated_header_is_refused(tiny_bundle, tmp_path):
    path = tmp_path / "cut.narf"
    path.write_bytes(tiny_bundle.read_bytes()[:200])
    assert_refused(path, "not a NARF model bundle")


@pytest.mark.slow
def test_a_grid_of_another_shape_than_its_bits_is_refused(tiny_bundle, tmp_path):
    def grow(meta: dict) -> dict:
        return {**meta, "grid_shape": [2 * s for s in meta["grid_shape"]]}

    path = rewrite_metadata(tiny_bundle, tmp_path / "shape.narf", grow)
    assert_refused(path, "incomplete or inconsistent", "packed occupancy grid of shape")


@pytest.mark.slow
@pytest.mark.parametrize(("drop", "words"), [("grid", "'grid'"), ("part_grid.1", "'part_grid.1'"), ("points.", "mesh")])
def test_a_bundle_without_some_of_its_tensors_is_refused(tiny_bundle, tmp_path, drop, words):
    tensors = {k: v for k, v in load_file(str(tiny_bundle)).items() if not k.startswith(drop)}
    path = tmp_path / "missing.narf"
    save_file(tensors, str(path), metadata=unchecked_metadata(tiny_bundle))
    assert_refused(path, "incomplete or inconsistent", words)


@pytest.mark.slow
def test_weights_of_the_wrong_shape_are_refused(tiny_bundle, tmp_path):
    tensors = load_file(str(tiny_bundle))
    name = next(k for k in tensors if k.startswith("field."))
    tensors[name] = torch.zeros(1)
    path = tmp_path / "shape.narf"
    save_file(tensors, str(path), metadata=unchecked_metadata(tiny_bundle))
    assert_refused(path, "incomplete or inconsistent")


@pytest.mark.parametrize("camera", [{"width": 160, "height": 120, "fx": "wide", "fy": 134.1},
                                    {"width": 160, "height": 120, "fx": -1.0, "fy": 134.1}, {"fx": 134.1}, [1, 2]])
def test_a_malformed_training_camera_is_refused(tiny_bundle, tmp_path, camera):
    path = rewrite_metadata(tiny_bundle, tmp_path / "camera.narf", lambda m: {**m, "training_camera": camera})
    assert_refused(path, "incomplete or inconsistent", "training_camera must hold positive numbers")
    good = {"width": 160, "height": 120, "fx": 134.125, "fy": 134.125}
    path = rewrite_metadata(tiny_bundle, tmp_path / "good.narf", lambda m: {**m, "training_camera": good})
    assert load_bundle(path).metadata["training_camera"] == good


@pytest.mark.slow
def test_broken_urdf_in_the_metadata_is_refused(tiny_bundle, tmp_path):
    path = rewrite_metadata(tiny_bundle, tmp_path / "urdf.narf", lambda m: {**m, "urdf": "<robot name='x'>"})
    assert_refused(path, "incomplete or inconsistent")


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda m: {**m, "field": {**m["field"], "arch": "nerf"}}, "unknown field architecture 'nerf'"),
        (lambda m: {**m, "field": {**m["field"], "layers": "two"}}, "incomplete or inconsistent"),
        (lambda m: {**m, "grid_aabb": [[0, 0, 0], [0, 0, 0]]}, "grid aabb"),
        (lambda m: {k: v for k, v in m.items() if k != "name"}, "'name'"),
    ],
    ids=["arch", "hyper-parameter", "grid-box", "name"],
)
@pytest.mark.slow
def test_inconsistent_metadata_is_refused_naming_the_file(tiny_bundle, tmp_path, change, words):
    path = rewrite_metadata(tiny_bundle, tmp_path / "odd.narf", change)
    assert_refused(path, "incomplete or inconsistent", words)


# ---------------------------------------------------------------------------------------------
# The model's API: modes and joints


@pytest.mark.slow
def test_parts_mode_without_part_fields_is_a_value_error(tiny_model, tiny_dataset):
    T, joints, camera = first_test_view(tiny_dataset)
    narf_only = dataclasses.replace(tiny_model, part_fields=None, part_grids=None)
    assert not narf_only.has_parts and narf_only.describe()["modes"] == ["narf"]
    with pytest.raises(ValueError, match="no part fields.*'parts' is unavailable"):
        narf_only.render(T, narf_only.joint_vector(joints), camera, mode="parts")
    assert narf_only.render(T, narf_only.joint_vector(joints), camera)["rgb"].shape == (36, 48, 3)


@pytest.mark.slow
def test_a_bundle_saved_without_parts_loads_without_parts(tiny_model, tmp_path):
    narf_only = dataclasses.replace(tiny_model, part_fields=None, part_grids=None)
    copy = load_bundle(save_bundle(tmp_path / "m.narf", narf_only))
    assert not copy.has_parts and read_metadata(tmp_path / "m.narf")["parts"] == []


@pytest.mark.slow
def test_an_unknown_render_mode_is_a_value_error(tiny_model, tiny_dataset):
    T, joints, camera = first_test_view(tiny_dataset)
    theta = tiny_model.joint_vector(joints)
    with pytest.raises(ValueError, match="unknown render mode 'nerf'; expected one of auto, narf, parts"):
        tiny_model.render(T, theta, camera, mode="nerf")
    with pytest.raises(ValueError, match="unknown render mode"):
        tiny_model.render_rays(camera.rays().transform(torch.eye(4)), theta, mode="")


@pytest.mark.parametrize(
    ("joints", "words"),
    [
        ({"pivo": 0.1}, ["unknown joint", "'pivo'", "pivot"]),
        ({"pivot": 0.7}, ["'pivot'", "0.7", "outside its limits"]),
        ({"pivot": -0.01}, ["'pivot'", "outside its limits"]),
        ({"pivot": math.nan}, ["'pivot'", "finite"]),
        ({"pivot": math.inf}, ["'pivot'", "finite"]),
        ({"pivot": "0.1"}, ["'pivot'", "number"]),
    ],
)
@pytest.mark.slow
def test_joint_vector_errors_name_the_joint(tiny_model, joints, words):
    with pytest.raises(ValueError) as info:
        tiny_model.joint_vector(joints)
    for w in words:
        assert w in str(info.value), str(info.value)


@pytest.mark.slow
def test_joint_vector_accepts_the_limits_and_fills_mid_range(tiny_model):
    assert tiny_model.joint_vector(None).tolist() == pytest.approx([0.3])
    assert tiny_model.joint_vector({"pivot": 0.0}).tolist() == [0.0]
    upper = tiny_model.joint_vector({"pivot": 0.6})
    assert upper.dtype == torch.float32 and float(upper) == pytest.approx(0.6)
    assert tiny_model.joint_dict(upper) == {"pivot": pytest.approx(0.6)}


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["narf", "parts"])
def test_one_theta_per_ray_renders_as_a_shared_theta(tiny_model, tiny_dataset, mode):
    """The refiner batches several θ starts as one θ per ray; that must render like a shared θ."""
    from narf_core.geometry import invert_pose

    frame = Dataset.open(tiny_dataset).frames("test")[0]
    camera = Dataset.open(tiny_dataset).camera
    rays = camera.rays().transform(invert_pose(torch.as_tensor(frame.T_cam_obj, dtype=torch.float32)))
    theta = tiny_model.joint_vector(frame.joints)
    shared = tiny_model.render_rays(rays, theta, mode=mode, outputs=("rgb", "opacity"))
    per_ray = tiny_model.render_rays(rays, theta.expand(len(rays), -1).contiguous(), mode=mode, outputs=("rgb", "opacity"))
    assert shared.opacity.max() > 0.5
    # A shared θ also clips rays to its bin's tight box, so a ray may march one sample more or less
    # at the box edge (measured: at most 0.005 in opacity on this tiny model); nothing else differs.
    assert torch.allclose(shared.rgb, per_ray.rgb, atol=1e-2)
    assert torch.allclose(shared.opacity, per_ray.opacity, atol=1e-2)
    assert (shared.rgb - per_ray.rgb).abs().mean() < 1e-4


# ---------------------------------------------------------------------------------------------
# Integrity: the tensors' checksum and finite weights

BUNDLED = Path(__file__).resolve().parent.parent / "models" / "clamp.narf"


def test_the_bundled_model_carries_a_verified_checksum():
    meta = read_metadata(BUNDLED)
    assert meta["checksum"]["algorithm"] == "sha256"
    assert meta["checksum"]["tensors"] == tensors_digest(load_file(str(BUNDLED)))
    assert load_bundle(BUNDLED).name == "clamp"


def test_a_flipped_weight_byte_is_refused(tmp_path):
    raw = bytearray(BUNDLED.read_bytes())
    raw[-1001] ^= 0x10  # a byte of the last tensor's data, far from the header
    path = tmp_path / "flipped.narf"
    path.write_bytes(bytes(raw))
    assert_refused(path, "checksum mismatch")


def test_non_finite_weights_are_refused_even_with_a_matching_checksum(tmp_path):
    model = load_bundle(BUNDLED)
    name, weight = next((k, v) for k, v in model.field.state_dict().items() if v.is_floating_point())
    weight.fill_(float("nan"))  # the loaded model's own tensor: saved as is, with a checksum of the NaNs
    path = save_bundle(tmp_path / "nan.narf", model)
    assert read_metadata(path)["checksum"]["tensors"] == tensors_digest(load_file(str(path)))
    assert_refused(path, "non-finite weights in", f"field.{name}", f"({weight.numel()} of {weight.numel()} values)")


def test_a_bundle_saved_before_checksums_loads_with_the_finiteness_check_only(tmp_path):
    path = tmp_path / "old.narf"
    save_file(load_file(str(BUNDLED)), str(path), metadata=unchecked_metadata(BUNDLED))
    assert "checksum" not in read_metadata(path) and load_bundle(path).name == "clamp"
    tensors = load_file(str(BUNDLED))
    key = next(k for k, v in tensors.items() if v.is_floating_point())
    tensors[key].view(-1)[0] = float("inf")
    save_file(tensors, str(path), metadata=unchecked_metadata(BUNDLED))
    assert_refused(path, "non-finite weights in", key, "(1 of")


# ---------------------------------------------------------------------------------------------
# An articulated field copied from the part fields is stored once (as the parts)


def articulated_clamp():
    """The bundled clamp with the articulated field built from its parts (as ``narf train`` builds it)."""
    from narf_core.fields import ArticulatedField

    model = load_bundle(BUNDLED)
    field = ArticulatedField.from_parts(model.kinematics, model.part_fields, model.part_grids, model.aabb)
    return dataclasses.replace(model, field=field.eval().requires_grad_(False))


def clamp_view(model):
    from narf_core.geometry import Pinhole, invert_pose, look_at

    center = ((model.aabb[0] + model.aabb[1]) / 2).double()
    eye = center + torch.tensor([0.2, -0.25, 0.15], dtype=torch.float64)
    T_cam_obj = invert_pose(look_at(eye, center, torch.tensor([0, 0, 1.0], dtype=torch.float64))).float()
    return T_cam_obj, (model.lower + model.upper) / 2, Pinhole.primesense(64, 48)


def test_an_articulated_bundle_stores_its_parts_once_and_renders_as_before(tmp_path, monkeypatch):
    """The field is rebuilt from the stored part fields at load: the same weights, the same images in
    both modes, and a file about the size of one copy of the parts (the legacy layout, still read,
    stored the atlas beside them)."""
    import narf_core.bundle as bundle

    model = articulated_clamp()
    path = save_bundle(tmp_path / "once.narf", model)
    assert read_metadata(path)["field_from_parts"] is True and read_metadata(path)["version"] == FORMAT_VERSION
    assert not any(key.startswith("field.") for key in load_file(str(path)))
    monkeypatch.setattr(bundle, "_field_from_parts", lambda m: False)
    monkeypatch.setattr(bundle, "FORMAT_VERSION", 2)
    legacy = save_bundle(tmp_path / "twice.narf", model)
    monkeypatch.undo()
    assert read_metadata(legacy)["version"] == 2 and any(key.startswith("field.atlas") for key in load_file(str(legacy)))
    field_bytes = sum(t.numel() * t.element_size() for t in model.field.state_dict().values())
    assert path.stat().st_size < legacy.stat().st_size - 0.95 * field_bytes  # the atlas is not stored again
    assert path.stat().st_size < 0.3 * legacy.stat().st_size

    T_cam_obj, theta, camera = clamp_view(model)
    before = {mode: model.render(T_cam_obj, theta, camera, outputs=("rgb", "opacity"), mode=mode) for mode in ("narf", "parts")}
    assert float(before["parts"]["opacity"].max()) > 0.5
    for saved in (path, legacy):
        copy = load_bundle(saved)
        ours, theirs = model.field.state_dict(), copy.field.state_dict()
        assert ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in ours)
        for mode, images in before.items():
            after = copy.render(T_cam_obj, theta, camera, outputs=("rgb", "opacity"), mode=mode)
            assert all(torch.equal(images[k], after[k]) for k in images), (saved.name, mode)


def test_an_articulated_field_changed_after_the_copy_is_stored_whole(tmp_path):
    model = articulated_clamp()
    with torch.no_grad():
        model.field.atlas[0, 0, 0] += 1.0  # no longer what the parts rebuild
    path = save_bundle(tmp_path / "tuned.narf", model)
    assert read_metadata(path)["field_from_parts"] is False
    copy = load_bundle(path)
    assert torch.equal(copy.field.atlas, model.field.atlas)
    assert not torch.equal(copy.field.atlas, articulated_clamp().field.atlas)


def test_a_bundle_whose_parts_do_not_rebuild_its_field_config_is_refused(tmp_path):
    path = save_bundle(tmp_path / "once.narf", articulated_clamp())
    changed = rewrite_metadata(path, tmp_path / "changed.narf", lambda m: {**m, "field": {**m["field"], "hidden": 32}})
    assert_refused(changed, "incomplete or inconsistent model bundle", "differs from the bundle's field config")


# Dense surface points added to a bundle saved without them (``narf points``)


def test_narf_points_adds_the_training_meshes_dense_points_and_refuses_other_meshes(bundled_clamp, tmp_path, capsys):
    """A bundle saved without dense points loads with none; ``narf points`` samples them from the URDF it was trained
    on (the clamp of seed 0, whose 500 points a link are the bundle's), and refuses in one line other meshes (the bar
    scaled by 1 %) and another object, leaving the bundle as it was."""
    from narf_core.cli import EXIT_ERROR, main
    from narf_core.data.synth.tools import build_tool
    from narf_core.kinematics import KinematicTree

    old = save_bundle(tmp_path / "old.narf", dataclasses.replace(bundled_clamp, dense_points={}))
    assert load_bundle(old).dense_points == {}
    own = build_tool("clamp", tmp_path / "own", seed=0)
    assert main(["points", str(old), "--urdf", str(own), "--out", str(tmp_path / "new.narf")]) == 0
    assert "bar 2053, moving_jaw 570 dense points" in capsys.readouterr().out
    new = load_bundle(tmp_path / "new.narf")
    expected = KinematicTree.from_urdf(own).dense_points()
    assert new.dense_points.keys() == expected.keys() == {"bar", "moving_jaw"}
    for name, points in expected.items():
        np.testing.assert_allclose(new.dense_points[name], points, rtol=0, atol=1e-6)  # stored as float32
    scaled = own.with_name("scaled.urdf")  # the bar's mesh 1 % larger
    scaled.write_text(own.read_text().replace('<mesh filename="meshes/bar.obj" />',
                                              '<mesh filename="meshes/bar.obj" scale="1.01 1.01 1.01" />', 1))
    for urdf, words in [(scaled, "link 'bar''s meshes are not the ones 'clamp' was trained on"),
                        (build_tool("gripper", tmp_path / "gripper", seed=0), "are not the model's")]:
        before = old.read_bytes()
        assert main(["points", str(old), "--urdf", str(urdf)]) == EXIT_ERROR
        err = capsys.readouterr().err.strip()
        assert err.startswith("narf points: error: ") and words in err and "\n" not in err
        assert old.read_bytes() == before
