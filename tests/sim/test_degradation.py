"""Square-patch depth corruption: coverage, patch sizes, seeding, the paper's presets."""

import pytest
import torch

from sim.degradation import (
    POLICY_PATCHES,
    RL_TRAINING,
    S1,
    S1_COVERAGE_LEVELS,
    S2,
    PatchScheme,
    ProjectorOffModel,
    corrupt_depth,
    corrupt_with_scheme,
    evaluation_scheme,
    patch_masks,
)


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


@pytest.mark.parametrize("coverage", [0.2, 0.3, 0.4, 0.5])
def test_evaluation_coverage_is_reached_overshooting_by_at_most_one_patch(coverage):
    scheme = evaluation_scheme(coverage)
    masks = patch_masks(torch.full((32,), coverage), scheme, _gen())
    frac = masks.float().mean(dim=(1, 2))
    assert torch.all(frac >= coverage)
    assert torch.all(frac <= coverage + 2 * 50 * 50 / 224**2)


def _shortest_row_run(masks):
    """Shortest run of masked pixels along any row (a union of squares of side >= s has no run < s)."""
    shortest = 10**9
    for row in masks.reshape(-1, masks.shape[-1]).int():
        edges = torch.diff(torch.cat([torch.zeros(1, dtype=torch.int32), row, torch.zeros(1, dtype=torch.int32)]))
        starts, ends = torch.nonzero(edges == 1).flatten(), torch.nonzero(edges == -1).flatten()
        if len(starts):
            shortest = min(shortest, int((ends - starts).min()))
    return shortest


def test_evaluation_patch_sides_can_be_chosen():
    masks = patch_masks(torch.full((8,), 0.5), evaluation_scheme(0.5, (100, 100)), _gen())
    assert torch.all(masks.float().mean(dim=(1, 2)) >= 0.5)
    assert _shortest_row_run(masks) >= 100
    assert _shortest_row_run(patch_masks(torch.full((8,), 0.5), evaluation_scheme(0.5), _gen())) < 100
    with pytest.raises(ValueError, match="patch sides 0..5 px"):
        evaluation_scheme(0.5, (0, 5))


def test_zero_coverage_leaves_images_pristine():
    assert not patch_masks(torch.zeros(4), evaluation_scheme(0.0), _gen()).any()


def test_patches_are_squares_of_the_scheme_sides():
    # One patch only: its bounding box is a square with a side in range.
    scheme = PatchScheme(50, 100, min_coverage=0.01, max_coverage=0.01)
    masks = patch_masks(torch.full((16,), 0.01), scheme, _gen(3))
    for mask in masks:
        rows, cols = mask.any(dim=1).nonzero(), mask.any(dim=0).nonzero()
        height, width = int(rows.max() - rows.min() + 1), int(cols.max() - cols.min() + 1)
        assert height == width and 50 <= height <= 100
        assert int(mask.sum()) == height * width


def test_same_seed_same_masks_other_seed_other_masks():
    cov = torch.full((8,), 0.3)
    a = patch_masks(cov, RL_TRAINING, _gen(1))
    b = patch_masks(cov, RL_TRAINING, _gen(1))
    c = patch_masks(cov, RL_TRAINING, _gen(2))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_s2_half_pristine_and_coverage_range():
    coverage = S2.sample_coverage(4000, _gen())
    pristine = coverage == 0
    assert 0.45 < pristine.float().mean() < 0.55
    assert coverage[~pristine].min() >= 0.2 and coverage[~pristine].max() <= 0.5


def test_policy_patches_are_the_policys_sides_at_s2s_coverages():
    coverage = POLICY_PATCHES.sample_coverage(4000, _gen())
    pristine = coverage == 0
    assert 0.45 < pristine.float().mean() < 0.55
    assert coverage[~pristine].min() >= 0.2 and coverage[~pristine].max() <= 0.5
    assert (POLICY_PATCHES.min_side_px, POLICY_PATCHES.max_side_px) == (RL_TRAINING.min_side_px, RL_TRAINING.max_side_px)


def test_s1_coverage_shares():
    coverage = S1.sample_coverage(20000, _gen())
    share_50 = (coverage == 0.5).float().mean()
    assert torch.isclose(coverage.unique(), torch.tensor(S1_COVERAGE_LEVELS)).all()
    assert 0.28 < share_50 < 0.32


def test_corrupt_sets_invalid_zero_and_keeps_the_rest():
    depth = torch.rand(6, 1, 224, 224) * 0.9 + 0.05
    out, masks = corrupt_with_scheme(depth, RL_TRAINING, _gen())
    assert torch.all(out[:, 0][masks] == 0.0)
    assert torch.equal(out[:, 0][~masks], depth[:, 0][~masks])
    assert corrupt_depth(depth[:, 0], masks).shape == (6, 224, 224)


def test_bad_scheme_is_named():
    with pytest.raises(ValueError, match="patch sides"):
        patch_masks(torch.full((1,), 0.2), PatchScheme(0, 10, 0.2, 0.2), _gen())


def _scene(gray_std: float, gray_mean: float = 120.0, depth_m: float = 3.0, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    gray = (gray_mean + gray_std * torch.randn(2, 60, 80, generator=g)).clamp(0, 255).to(torch.uint8)
    return torch.full((2, 60, 80), depth_m), gray


def test_projector_off_loses_depth_by_its_cues():
    model = ProjectorOffModel()
    fx = 100.0
    textured = model.apply(*_scene(20.0), fx, _gen())[1].mean()
    flat = model.apply(*_scene(0.0), fx, _gen())[1].mean()
    dark = model.apply(*_scene(20.0, gray_mean=5.0), fx, _gen())[1].mean()
    far = model.apply(*_scene(20.0, depth_m=9.5), fx, _gen())[1].mean()
    assert textured < 0.1 and flat > 0.9 and dark > 0.5 and far > 0.9
    # A floor seen at a grazing angle: depth changes fast across the image.
    depth = torch.linspace(1.0, 9.0, 60).view(1, 60, 1).expand(2, 60, 80).contiguous()
    grazing = model.apply(depth, _scene(20.0)[1], fx, _gen())[1].mean()
    assert grazing > textured


def test_projector_off_output_and_seeding():
    depth, gray = _scene(2.0)
    out_a, frac_a = ProjectorOffModel().apply(depth, gray, 100.0, _gen(5))
    out_b, frac_b = ProjectorOffModel().apply(depth, gray, 100.0, _gen(5))
    assert torch.equal(out_a, out_b) and torch.equal(frac_a, frac_b)
    lost = out_a == 0
    assert torch.allclose(frac_a, lost.float().mean(dim=(1, 2)))
    assert torch.equal(out_a[~lost], depth[~lost])
    harsher = ProjectorOffModel(severity=2.0).apply(depth, gray, 100.0, _gen(5))[1]
    assert torch.all(harsher >= frac_a)
