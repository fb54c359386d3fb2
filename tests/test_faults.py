"""The sensor and segmenter faults of the shifted test sets, each on small arrays."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("scipy")

from narf_core.data.synth import faults  # noqa: E402


def _disc_mask(h: int = 60, w: int = 80, r: float = 18.0) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    return (y - h / 2) ** 2 + (x - w / 2) ** 2 <= r * r


def test_stereo_noise_grows_with_z_squared_and_keeps_holes() -> None:
    rng = np.random.default_rng(0)
    depth = np.zeros((200, 200), np.float32)
    depth[:, :100], depth[:, 100:150] = 0.5, 1.5  # the rest: no return
    noisy = faults.stereo_depth_noise(depth, rng, fx=500.0, baseline_m=0.05, disparity_std_px=0.1)
    near = (noisy[:, :100] - 0.5).std()
    far = (noisy[:, 100:150] - 1.5).std()
    assert near == pytest.approx(0.5**2 * 0.1 / (500 * 0.05), rel=0.1)  # 1 mm at 0.5 m
    assert far / near == pytest.approx(9.0, rel=0.15)
    assert (noisy[:, 150:] == 0).all()


def test_quantisation_to_millimetres() -> None:
    depth = np.array([[0.0, 0.70049, 0.70051, 1.23456]], np.float32)
    q = faults.quantise_depth(depth)
    assert q[0].tolist() == pytest.approx([0.0, 0.700, 0.701, 1.235], abs=1e-6)
    assert np.allclose(np.round(q * 1000), q * 1000, atol=1e-3)


def test_depth_holes_at_silhouette_edges_and_thin_parts() -> None:
    depth = np.full((40, 60), 1.0, np.float32)
    mask = np.zeros((40, 60), bool)
    mask[10:30, 10:30] = True  # a thick part at 0.5 m
    mask[20, 35:55] = True  # a one-pixel-thin part
    depth[mask] = 0.5
    holes = faults.depth_holes(depth, mask, np.random.default_rng(0), edge_px=1, edge_drop=1.0, thin_px=1, speckle=0.0)
    # every pixel beside a depth jump is dropped, on both sides of it
    assert (holes[10:30, 9:11] == 0).all() and (holes[9:11, 10:30] == 0).all()
    assert (holes[20, 35:55] == 0).all()  # the thin part is gone
    assert (holes[13:27, 13:27] == 0.5).all()  # the inside of the thick part stays
    assert (holes[:, 58:] == 1.0).all()  # far from any jump, the background stays
    fewer = faults.depth_holes(depth, mask, np.random.default_rng(0), edge_px=1, edge_drop=0.3, thin_px=0, speckle=0.0)
    dropped = (fewer == 0).sum() / (faults.depth_discontinuities(depth, 0.02)).sum()
    assert 0.15 < dropped < 0.45


@pytest.mark.parametrize("fraction", [0.05, 0.2, 0.4])
def test_occluder_hides_the_asked_share_of_the_tool(fraction: float) -> None:
    mask = _disc_mask()
    mask[5:10, 5:70] = True  # not convex: a handle
    for seed in range(3):
        region = faults.occluder_region(mask, np.random.default_rng(seed), fraction)
        hidden = (region & mask).sum() / mask.sum()
        assert hidden == pytest.approx(fraction, abs=0.01)
    assert not faults.occluder_region(mask, np.random.default_rng(0), 0.0).any()


def test_composited_occluder_is_in_front_of_the_tool() -> None:
    mask = _disc_mask()
    linear = np.full((*mask.shape, 3), 0.3, np.float32)
    depth = np.where(mask, 0.8, 1.2).astype(np.float32)
    region = faults.occluder_region(mask, np.random.default_rng(1), 0.3)
    out, z = faults.composite_occluder(linear, depth, region, np.random.default_rng(1), tool_depth=0.8)
    assert (z[region] < 0.8).all() and (z[region] > 0.6).all()
    assert (z[~region] == depth[~region]).all() and (out[~region] == linear[~region]).all()
    assert not np.allclose(out[region], 0.3)


def test_occluder_is_in_front_of_every_part_it_hides_on_an_oblique_tool() -> None:
    # a long tool seen obliquely: its near end 30 cm nearer than its median, the occluder placed anywhere
    mask = np.zeros((60, 80), bool)
    mask[25:35, 5:75] = True
    depth = np.where(mask, np.linspace(0.6, 1.2, 80)[None], 1.5).astype(np.float32)
    linear = np.full((60, 80, 3), 0.3, np.float32)
    labels = mask.astype(np.uint8)
    for seed in range(12):
        f = faults.apply_faults(linear, depth, labels, faults.condition("occlusion-40"), (seed, 0), fx=60.0)
        hidden = mask & (f.labels == 0)
        assert hidden.any()
        assert (f.depth[hidden] < depth[hidden] - 0.005).all(), f"seed {seed}: the occluder lies behind a part it hides"


def test_a_sequences_occluder_is_one_object_moving_round_the_tool() -> None:
    """With a sequence's seed the occluder hides the asked share in every frame and moves a little from one
    frame to the next (30 frames/s) while the tool slides; drawn per frame, it jumps round the tool."""
    linear = np.full((60, 80, 3), 0.3, np.float32)

    def centres(sequence: bool) -> tuple[np.ndarray, list[float]]:
        out, directions = [], []
        for k in range(30):
            mask = np.roll(_disc_mask(), k // 2, axis=1)  # the tool slides half a pixel per frame
            depth = np.where(mask, 0.8, 1.2).astype(np.float32)
            f = faults.apply_faults(linear, depth, mask.astype(np.uint8), faults.condition("occlusion-20"), (7, k),
                                    fx=60.0, sequence_seed=(7,) if sequence else None, time=k / 30)
            assert (mask & (f.labels == 0)).sum() / mask.sum() == pytest.approx(0.2, abs=0.02)
            region = f.depth != depth
            out.append(np.argwhere(region).mean(0))
            directions.append(f.info.get("occluder_direction_deg"))
        return np.diff(np.array(out), axis=0), directions

    moved, directions = centres(sequence=True)
    assert np.hypot(*moved.T).max() < 3.0
    turned = np.diff(np.unwrap(np.radians(directions)))
    assert np.allclose(turned, turned[0]) and 10 <= abs(np.degrees(turned[0])) * 30 <= 40  # degrees per second
    jumped, none = centres(sequence=False)
    assert np.hypot(*jumped.T).mean() > 5 * np.hypot(*moved.T).mean() and none == [None] * 30


def test_mask_erosion_and_dilation_by_the_asked_pixels() -> None:
    mask = np.zeros((40, 40), bool)
    mask[10:30, 10:30] = True
    eroded = faults.grow_mask(mask, -2)
    assert eroded.sum() == 16 * 16 and eroded[12:28, 12:28].all()
    dilated = faults.grow_mask(mask, 2)
    assert dilated[20, 8] and not dilated[20, 7] and dilated[8, 20] and not dilated[7, 20]
    assert dilated[mask].all() and dilated.sum() > mask.sum()
    assert (faults.grow_mask(mask, 0) == mask).all()


def test_blob_errors_remove_inside_or_add_outside() -> None:
    mask = _disc_mask()
    missing = faults.mask_blob(mask, np.random.default_rng(0), 6.0, extra=False)
    extra = faults.mask_blob(mask, np.random.default_rng(0), 6.0, extra=True)
    assert not (missing & ~mask).any() and 40 < (mask & ~missing).sum() <= np.pi * 36 + 10
    assert not (mask & ~extra).any() and 20 < (extra & ~mask).sum() <= np.pi * 36 + 10


def test_soft_edge_changes_only_the_boundary() -> None:
    mask = _disc_mask(r=20)
    soft = faults.soft_edge_mask(mask, np.random.default_rng(0), sigma_px=1.5, wobble=0.3)
    changed = soft != mask
    assert changed.any()
    y, x = np.nonzero(changed)
    radius = np.hypot(y - 30, x - 40)
    assert (np.abs(radius - 20) < 5).all()


def test_shot_and_read_noise_variance() -> None:
    rng = np.random.default_rng(0)
    for level in (0.05, 0.5):
        x = np.full((300, 300, 3), level, np.float32)
        y = faults.shot_read_noise(x, rng, full_well=1000.0, read_std=0.01)
        assert y.var() == pytest.approx(level / 1000 + 0.01**2, rel=0.05)
        assert y.mean() == pytest.approx(level, abs=2e-3)


def test_tone_curve_exposure_and_jpeg() -> None:
    x = np.linspace(0, 1, 256, dtype=np.float32).reshape(16, 16, 1).repeat(3, -1)
    assert np.abs(faults.to_linear(faults.to_srgb(x)) - x).max() < 0.01
    assert (faults.to_srgb(x * 4)[x > 0.25] == 255).all()  # clipped
    brighter = faults.exposure_white_balance(x, 1.0, (1.0, 0.5, 2.0))
    assert np.allclose(brighter, x * 2 * np.array([1.0, 0.5, 2.0]))
    rgb = faults.to_srgb(x)
    decoded = faults.jpeg(rgb, 90)
    assert decoded.shape == rgb.shape and decoded.dtype == np.uint8
    assert np.abs(decoded.astype(int) - rgb).mean() < 3


def _scene():
    rng = np.random.default_rng(5)
    h, w = 48, 64
    labels = np.zeros((h, w), np.uint8)
    labels[14:34, 12:40] = 1
    labels[20:26, 40:56] = 2
    linear = rng.uniform(0.05, 0.6, (h, w, 3)).astype(np.float32)
    depth = np.where(labels > 0, 0.7, 1.1).astype(np.float32)
    return linear, depth, labels


def test_conditions_are_deterministic_and_share_their_draws() -> None:
    linear, depth, labels = _scene()
    out = {name: faults.apply_faults(linear, depth, labels, faults.condition(name), (3, 7), fx=60.0)
           for name in faults.CONDITIONS}
    again = faults.apply_faults(linear, depth, labels, faults.condition("all"), (3, 7), fx=60.0)
    assert (again.rgb == out["all"].rgb).all() and (again.depth == out["all"].depth).all()
    assert (again.labels == out["all"].labels).all()
    other = faults.apply_faults(linear, depth, labels, faults.condition("all"), (4, 7), fx=60.0)
    assert (other.rgb != out["all"].rgb).any()
    clean = out["lighting"]
    assert (clean.labels == labels).all() and (clean.depth == depth).all()
    assert (out["depth"].rgb == clean.rgb).all() and (out["depth"].depth != depth).any()
    assert (out["noise"].labels == labels).all() and (out["noise"].rgb != clean.rgb).any()
    assert (out["mask"].rgb == clean.rgb).all() and (out["mask"].labels != labels).any()
    assert np.allclose(out["depth"].depth * 1000, np.round(out["depth"].depth * 1000), atol=1e-3)
    for name in ("occlusion-20", "occlusion-40"):
        f = out[name]
        assert f.info["occluded"] == pytest.approx(float(name[-2:]) / 100, abs=0.02)
        assert (f.labels > 0).sum() / (labels > 0).sum() == pytest.approx(1 - f.info["occluded"], abs=1e-6)
        assert (f.clean_labels == labels).all()
    # a faulty mask keeps the links: every labelled pixel carries the label of the nearest true part
    assert set(np.unique(out["mask"].labels)) <= {0, 1, 2}
    with pytest.raises(ValueError, match="unknown condition 'fog'"):
        faults.condition("fog")


def test_pixel_sized_faults_scale_with_the_camera() -> None:
    """The mask's growth and soft edge, the blur and the depth holes' widths are the native camera's pixels:
    at a quarter of its fx a thin tool's mask keeps its pixels (a 2-pixel erosion at 640x480 is half a pixel
    at 160x120) and its thin parts keep their depth, while at the native fx the same draws erode and drop
    them; the drawn values say so."""
    mask = np.zeros((60, 80), bool)
    mask[20:22, 10:70] = True  # a handle two pixels wide
    mask[30:40, 30:50] = True
    labels = mask.astype(np.uint8)
    depth = np.where(mask, 0.6, 0.0).astype(np.float32)
    linear = np.full((60, 80, 3), 0.3, np.float32)
    options = faults.FaultOptions(mask=True, depth=True, mask_grow_px=(-2, -2), blob_radius=0.0, speckle=0.0,
                                   edge_drop=0.0)
    native = faults.apply_faults(linear, depth, labels, options, (0, 1), options.native_fx)
    quarter = faults.apply_faults(linear, depth, labels, options, (0, 1), options.native_fx / 4)
    assert native.info["mask_grow_px"] == -1 and quarter.info["mask_grow_px"] == 0
    kept = lambda f: ((f.labels > 0) & mask).sum() / mask.sum()  # noqa: E731
    assert kept(quarter) > 0.9 > kept(native)
    handle = np.zeros_like(mask)
    handle[20:22, 15:65] = True
    assert (native.depth[handle] == 0).all() and (quarter.depth[handle] > 0).mean() > 0.9
