"""Which pixels the refiner looks at, and how it compares them (issue #15): stratified and edge rays,
more rays for a larger box, gain/bias compensation, robust costs,
occlusion gating and how far the mask is trusted (its boundary band, the rays outside it) in the
Adam refiner's loss; on the analytic toy clamp of tests/test_estimate.py."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from narf_core.estimate import (
    EstimateInputError,
    EstimateOptions,
    _gain_bias,
    _mask_band,
    _mask_box,
    _observation,
    _occluded,
    _outside_weight,
    _box_scale,
    _ray_index,
    _robust,
    _stratified,
    refine,
    weighs_outside,
)
from tests.test_estimate import ASSETS, CAMERA, TRUTH, SliderField, make_model, observe, perturbed, view

FAST = dict(iterations=80, rays_per_iteration=512, lr_pose=0.02, theta_starts=1, uncertainty=False)


@pytest.fixture(scope="module")
def model():
    return make_model(SliderField(), ASSETS)


def _disc(h: int, w: int, radius: float) -> np.ndarray:
    v, u = np.mgrid[:h, :w]
    return (u - w / 2) ** 2 + (v - h / 2) ** 2 <= radius**2


def test_stratified_rays_put_one_ray_in_every_cell():
    """A 40x40 box and 100 rays: a 10x10 grid of 4x4-pixel cells, one ray in each (independent draws
    would leave about a third of the cells empty)."""
    index = _stratified((40, 40), 100, torch.Generator().manual_seed(0))
    v, u = index // 40, index % 40
    cells = (v // 4) * 10 + u // 4
    assert sorted(cells.tolist()) == list(range(100))
    more = _stratified((30, 50), 4000, torch.Generator().manual_seed(1))  # more rays than pixels: all in the box
    assert len(more) == 4000 and 0 <= int(more.min()) and int(more.max()) < 1500


def test_edge_rays_lie_on_the_mask_edge():
    """``ray_sampling = "edges"``: half the rays drawn on the mask's edge band (a small share of the
    box), so most of those land in it; ``"auto"`` switches to it in a box above the reference size."""
    mask = _disc(240, 320, 60)
    image = np.zeros((240, 320, 3), np.uint8)
    obs = _observation(image, mask, None, _mask_box(mask, 0.15), 1, "cpu")
    u, v = obs.pixels[:, 0].numpy(), obs.pixels[:, 1].numpy()
    distance = np.abs(np.hypot(u + 0.5 - 160, v + 0.5 - 120) - 60)
    band = distance <= 2.5
    assert band.mean() < 0.15
    index = _ray_index(obs, EstimateOptions(ray_sampling="edges"), 1024, torch.Generator().manual_seed(0), False)
    assert band[index.numpy()].mean() > 0.4
    uniform = _ray_index(obs, EstimateOptions(), 1024, torch.Generator().manual_seed(0), False)
    assert band[uniform.numpy()].mean() < 0.2
    auto = EstimateOptions(ray_sampling="auto")  # uniform in a box of the reference size, edges in a larger one
    assert torch.equal(_ray_index(obs, auto, 1024, torch.Generator().manual_seed(0), False), uniform)
    obs.scale = 2
    assert torch.equal(_ray_index(obs, auto, 1024, torch.Generator().manual_seed(0), False), index)


def test_a_larger_box_draws_more_rays(model, monkeypatch):
    """``reference_box_px``: a box k times that side (at least 1, at most 4) draws k times the rays
    per iteration; 0 = off."""
    big, small = (100, 50, 400, 250), (10, 10, 90, 60)  # (u0, v0, u1, v1): 300 and 80 pixels wide
    opts = EstimateOptions(reference_box_px=120)
    assert _box_scale(big, opts) == 2.5 and _box_scale(small, opts) == 1
    assert _box_scale(big, EstimateOptions()) == 1
    assert _box_scale(big, EstimateOptions(reference_box_px=10)) == 4  # capped
    with pytest.raises(EstimateInputError, match="options.reference_box_px"):
        EstimateOptions(reference_box_px=-1)

    import narf_core.estimate as estimate

    drawn = []
    real = estimate._ray_index
    monkeypatch.setattr(estimate, "_ray_index", lambda obs, o, n, *a: drawn.append(n) or real(obs, o, n, *a))
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    run = dict(iterations=3, rays_per_iteration=64, theta_starts=1, uncertainty=False, early_stop=False)
    refine(model, image, mask, CAMERA, T, joints_init=TRUTH, options=EstimateOptions(**run))
    refine(model, image, mask, CAMERA, T, joints_init=TRUTH, options=EstimateOptions(reference_box_px=8, **run))
    assert drawn == [64] * 3 + [256] * 3


def test_gain_and_bias_are_recovered_in_closed_form():
    """An observation 0.7x as bright plus 0.1 (per channel), premultiplied by the mask; rays off the
    mask or off the render do not count."""
    g = torch.Generator().manual_seed(0)
    n = 200
    colour = torch.rand(1, n, 3, generator=g) * 0.8 + 0.1
    opacity = torch.ones(1, n)
    opacity[0, :20] = 0.0  # not rendered: ignored
    mask = torch.ones(n)
    mask[20:40] = 0.0  # not the object: ignored
    observed = (0.7 * colour[0] + torch.tensor([0.1, 0.05, 0.0])) * mask[:, None]
    observed[:20] = 0.9
    gain, bias = _gain_bias(colour * opacity[..., None], opacity, observed, mask, torch.ones(1, n, dtype=torch.bool))
    assert torch.allclose(gain, torch.full((1, 3), 0.7), atol=1e-4)
    assert torch.allclose(bias, torch.tensor([[0.1, 0.05, 0.0]]), atol=1e-4)
    few = torch.zeros(1, n, dtype=torch.bool)
    gain, bias = _gain_bias(colour, opacity, observed, mask, few)  # too few rays: identity
    assert torch.equal(gain, torch.ones(1, 3)) and torch.equal(bias, torch.zeros(1, 3))


def test_robust_costs_match_the_square_for_small_residuals_and_grow_slower():
    r2 = torch.tensor([1e-4, 0.01, 1.0])
    for kind in ("huber", "cauchy"):
        cost = _robust(r2, kind, 0.1)
        assert torch.allclose(cost[0], r2[0], rtol=0.01)
        assert float(cost[2]) < 0.25 * float(r2[2])
    assert torch.equal(_robust(r2, "none", 0.1), r2)


def test_rays_behind_an_occluder_are_flagged():
    """Observed depth well in front of the rendered surface: an occluder; within the margin, behind,
    without a return or off the render: not."""
    depth = torch.tensor([0.30, 0.49, 0.60, 0.0, 0.30])
    opacity = torch.tensor([[1.0, 1.0, 1.0, 1.0, 0.1]])
    rendered = 0.5 * opacity  # opacity-weighted surface depth 0.5 m
    assert _occluded(depth, rendered, opacity, 0.02).tolist() == [[True, False, False, False, False]]


def test_compensation_recovers_a_darker_view_with_adam(model):
    """The Adam refiner with ``photometric_compensation`` under a global gain and offset, and with
    occlusion gating and robust costs against a near occluder in the depth."""
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    dark = (image.astype(np.float64) * 0.6 + 12).clip(0, 255).astype(np.uint8)
    T0 = perturbed(T, 5, 0.01, seed=2)
    start = refine(model, dark, mask, CAMERA, T0, options=EstimateOptions(iterations=0, uncertainty=False),
                   ground_truth=(T, TRUTH))
    comp = refine(model, dark, mask, CAMERA, T0, ground_truth=(T, TRUTH),
                  options=EstimateOptions.robust(photometric_compensation=True, **FAST))
    assert comp.metrics["add"] < min(0.006, start.metrics["add"] / 2), (start.metrics, comp.metrics)
    occluded = depth.copy()
    rows = depth.shape[0] // 3
    occluded[:rows] = np.where(depth[:rows] > 0, 0.05, 0)  # a near occluder over the top third
    gated = refine(model, image, mask, CAMERA, T0, depth=occluded, ground_truth=(T, TRUTH),
                   options=EstimateOptions.robust(occlusion_margin=0.01, robust_loss="cauchy", robust_scale=0.3,
                                                  ray_sampling="stratified", **FAST))
    assert gated.metrics["add"] < 0.006, gated.metrics


def test_the_mask_band_is_the_pixels_near_its_boundary():
    """``_mask_band``: what a dilation by ``px`` adds and an erosion by ``px`` removes (chessboard
    distance): a 2-pixel band is 4 pixels wide across a straight edge and leaves the inside alone."""
    mask = torch.zeros(20, 30)
    mask[5:15, 8:22] = 1
    band = _mask_band(mask, 2)
    assert band[10].nonzero().flatten().tolist() == [6, 7, 8, 9, 20, 21, 22, 23]
    assert band[:, 15].nonzero().flatten().tolist() == [3, 4, 5, 6, 13, 14, 15, 16]
    assert not band[7:13, 10:20].any() and not band[:3].any() and not band[:, :6].any()
    obs = _observation(np.zeros((20, 30, 3), np.uint8), mask.numpy() > 0, None, (0, 0, 30, 20), 2, "cpu", 2)
    assert torch.equal(obs.levels[-1].band, band.reshape(-1)) and obs.levels[-1].image is not None
    assert obs.levels[0].image is None  # coarse levels keep the blurred mask everywhere
    assert _observation(np.zeros((20, 30, 3), np.uint8), mask.numpy() > 0, None, (0, 0, 30, 20), 1, "cpu").levels[0].band is None


@pytest.mark.parametrize("width", [1, 2, 3, 4, 5])
def test_the_mask_band_leaves_the_middle_of_a_thin_part(width):
    """A bar no wider than the 2-pixel band (5 pixels) would be band all through, leaving no pixel
    that says where the object is: its middle line (1 pixel for an odd width, 2 for an even one) stays
    out of the band, wherever its edges move as a whole; a thick block's band is unchanged."""
    mask = torch.zeros(24, 40)
    mask[3:13, 3:15] = 1  # thick: its band is the plain dilation minus erosion
    mask[16 : 16 + width, 20:36] = 1  # a horizontal bar
    band = _mask_band(mask, 2)
    middle = [16 + (width - 1) // 2, 16 + width // 2]
    for row in range(16, 16 + width):
        kept = not band[row, 22:34].any()
        assert kept == (row in middle) and band[row, 22:34].all() != kept, (width, row)
    assert band[3:13, 3:15].sum() == 10 * 12 - 6 * 8 and not band[5:11, 5:13].any()


def test_rays_outside_the_mask_weigh_less_unless_depth_sees_past_the_object():
    """``_outside_weight``: inside the mask and on its band 1, outside ``weight``; but a ray whose
    observed depth lies behind the rendered surface is background for sure (1), one outside the
    mask whose depth lies in front of it is an occluder's (0: no evidence either way), and one
    without a return or near the surface keeps ``weight``. In front inside the mask or on its
    band: 1 (the mask says the object is seen there)."""
    mask = torch.tensor([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0])
    edge = torch.tensor([False, True, False, False, False, False, False, True])
    opacity = torch.ones(1, 8)
    rendered = 0.5 * opacity  # the render's surface at 0.5 m
    depth = torch.tensor([0.5, 0.5, 0.0, 0.45, 0.505, 0.60, 0.45, 0.45])
    w = _outside_weight(mask, edge, depth, rendered, opacity, 0.25)
    assert w.tolist() == [[1.0, 1.0, 0.25, 0.0, 0.25, 1.0, 1.0, 1.0]]
    assert _outside_weight(mask, None, None, None, opacity, 0.25).tolist() == [[1.0] + [0.25] * 5 + [1.0, 0.25]]
    # at the full weight only an occluder's ray loses it, so the rule applies there only with a depth image
    assert _outside_weight(mask, edge, depth, rendered, opacity, 1.0).tolist() == [[1.0] * 3 + [0.0] + [1.0] * 4]
    partial = EstimateOptions(mask_trust="partial", outside_weight=1.0)
    assert weighs_outside(partial, depth) and not weighs_outside(partial, None)
    assert weighs_outside(replace(partial, outside_weight=0.3), None)
    assert not weighs_outside(replace(partial, mask_trust="full"), depth)
    with pytest.raises(EstimateInputError, match="options.outside_weight"):
        EstimateOptions(outside_weight=1.5)
    with pytest.raises(EstimateInputError, match="options.mask_band_px"):
        EstimateOptions(mask_band_px=-1)
    with pytest.raises(EstimateInputError, match="options.mask_trust"):
        EstimateOptions(mask_trust="some")
    with pytest.raises(EstimateInputError, match="options.partial_theta_starts"):
        EstimateOptions(partial_theta_starts=65)


def test_auto_mask_trust_is_partial_where_the_depth_contradicts_the_mask(model, monkeypatch):
    """``mask_trust = "auto"`` (the robust preset): an exact mask is trusted in full whatever the
    box size, with or without depth; partially where the depth shows an occluder beside the mask
    or a grown mask (its edge on the background surface behind); without depth (nothing then tells
    the background from an occluder) in full."""
    import narf_core.estimate as estimate

    bands, starts = [], []
    real, real_starts = estimate._observation, estimate._theta_starts
    monkeypatch.setattr(estimate, "_observation", lambda *a: bands.append(a[-1]) or real(*a))
    monkeypatch.setattr(estimate, "_theta_starts", lambda *a: starts.append(a[-1]) or real_starts(*a))
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    behind = float(depth[mask].max()) + 0.05
    wall = np.where(mask, depth, behind).astype(np.float32)  # a flat background behind the object
    occluded = wall.copy()
    cols = np.nonzero(mask.any(0))[0]
    hand = np.zeros_like(mask)
    hand[:, cols[int(0.7 * len(cols))]:] = True
    occluded[hand] = float(depth[mask].min()) - 0.05
    grown = _mask_band(torch.tensor(mask, dtype=torch.float32), 2).numpy() | mask
    run = dict(iterations=2, rays_per_iteration=64, theta_starts=2, partial_theta_starts=3, uncertainty=False,
               mask_trust="auto", depth_weight=1.0)
    cases = ((mask, depth, 0), (mask, wall, 1000), (mask, None, 8), (mask & ~hand, occluded, 0),
             (mask & ~hand, None, 0), (grown, wall, 0))
    for given_mask, given_depth, reference in cases:
        refine(model, image, given_mask, CAMERA, T, joints_init=TRUTH, depth=given_depth,
               options=EstimateOptions(reference_box_px=reference, **run))
    assert bands == [0, 0, 0, 3, 0, 3]
    assert starts == [2, 2, 2, 3, 2, 3]  # more configuration starts where the mask is trusted partially
    robust = EstimateOptions.robust()
    assert robust.mask_trust == "auto" and robust.partial_theta_starts > robust.theta_starts


def test_a_band_at_the_mask_edge_undoes_a_bled_mask(model):
    """A segmenter's mask grown by a pixel all round (4.5 mm at this size) pulls the estimate
    towards the camera; ignoring a 1-pixel band about the mask's edge (the render compared with
    the unmasked image there) gives most of that back."""
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    grown = _mask_band(torch.tensor(mask, dtype=torch.float32), 1).numpy() | mask
    T0 = perturbed(T, 5, 0.01, seed=0)
    adds = [refine(model, image, grown, CAMERA, T0, ground_truth=(T, TRUTH),
                   options=EstimateOptions.robust(mask_trust=trust, mask_band_px=1, outside_weight=1.0, **FAST)
                   ).metrics["add"] for trust in ("full", "partial")]
    assert adds[1] < min(0.01, adds[0] / 2), adds


def test_rays_outside_the_mask_count_less_under_an_occluder(model):
    """An occluder (grey) over the right quarter of the object, the mask its visible part: with
    the full weight outside the mask the estimate shrinks away from the hidden part; with
    ``outside_weight`` 0.3 it stays within a few millimetres."""
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    occluder = np.zeros_like(mask)
    occluder[:, int(np.percentile(np.nonzero(mask)[1], 75)):] = True
    image[occluder & mask] = 128
    T0 = perturbed(T, 5, 0.01, seed=1)
    adds = [refine(model, image, mask & ~occluder, CAMERA, T0, ground_truth=(T, TRUTH),
                   options=EstimateOptions.robust(mask_trust="partial", mask_band_px=0, outside_weight=w, **FAST)
                   ).metrics["add"] for w in (1.0, 0.3)]
    assert adds[1] < min(0.004, adds[0] / 2), adds
