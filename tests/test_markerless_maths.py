"""The markerless method's maths on synthetic arrays: back-substitution, signatures, state interpolation,
Laplacian lighting normalisation, gesture segmentation, co-articulation regions, model files."""

from __future__ import annotations

import numpy as np
import pytest

from livebridge.errors import InputError
from livebridge.markerless.analysis import Analyser, AnalysisState, RegionState, _RegionTables, classify_region
from livebridge.markerless.gestures import GestureConfig, find_gestures
from livebridge.markerless.model import MarkerlessModel, RegionModel
from livebridge.markerless.normalise import Normalisation, NormalisedFrame, lighting_normalise
from livebridge.markerless.regions import RegionConfig, co_articulation_regions
from livebridge.markerless.signatures import back_substitution, signature_basis, signatures
from livebridge.markerless.train import change_curves

pytest.importorskip("sklearn")


def test_back_substitution_is_the_least_squares_solution():
    rng = np.random.default_rng(0)
    basis = rng.normal(size=(500, 12))
    x = rng.normal(size=500)
    back = back_substitution(basis)
    expected = np.linalg.lstsq(basis, x, rcond=None)[0]
    np.testing.assert_allclose(back @ x, expected, atol=1e-10)
    # a rank-deficient basis: the minimum-norm solution, as a pseudo-inverse gives
    deficient = np.concatenate([basis, basis[:, :1]], axis=1)
    np.testing.assert_allclose(back_substitution(deficient) @ x, np.linalg.pinv(deficient) @ x, atol=1e-8)


@pytest.mark.parametrize("method", ["ica", "pca"])
def test_signature_basis_spans_the_samples_and_ica_unmixes_independent_sources(method):
    rng = np.random.default_rng(1)
    n_pixels = 4000
    sources = np.stack([rng.laplace(size=n_pixels), rng.uniform(-1, 1, n_pixels) ** 3,
                        np.sign(rng.normal(size=n_pixels)) * rng.exponential(size=n_pixels)], axis=1)
    mixing = rng.normal(size=(3, 40))
    samples = sources @ mixing
    basis = signature_basis(samples, n_components=3, method=method, seed=0)
    assert basis.shape == (n_pixels, 3)
    back = back_substitution(basis)
    reconstructed = basis @ (back @ samples)
    centred = samples - samples.mean(axis=0)
    np.testing.assert_allclose(reconstructed - reconstructed.mean(axis=0), centred, atol=1e-6 * np.abs(samples).max())
    if method == "ica":  # each independent source is found (up to sign and scale)
        correlation = np.abs(np.corrcoef(basis.T, sources.T)[:3, 3:])
        assert (correlation.max(axis=0) > 0.99).all()


def test_ica_keeps_every_source_of_a_region_with_many_samples_of_few_pixels():
    """A region of 585 pixels and 61 gesture frames, its principal images over two orders of magnitude: the
    ICA basis keeps all 24 directions, independent and spanning the samples' principal subspace. FastICA's own
    whitening (whiten_solver="eigh") of these orthogonal principal images collapsed its sources onto one image
    (condition number ~5e15), and the bench's eye and brow regions then read neutral whatever the face did."""
    rng = np.random.default_rng(0)
    images = rng.standard_normal((585, 30)) * np.geomspace(50, 1, 30)
    samples = images @ rng.standard_normal((30, 61)) + 5 * rng.standard_normal((585, 1))
    basis = signature_basis(samples, n_components=24, method="ica", seed=0)
    assert basis.shape == (585, 24)
    assert np.linalg.cond(basis) < 10
    principal = signature_basis(samples, n_components=24, method="pca")
    projected = principal @ np.linalg.lstsq(principal, basis, rcond=None)[0]
    np.testing.assert_allclose(projected, basis, atol=1e-6 * np.abs(basis).max())


@pytest.mark.parametrize("method", ["ica", "pca"])
def test_a_region_whose_samples_are_all_alike_has_a_zero_basis_and_no_signature(method):
    samples = np.full((50, 6), 3.0)  # a region no gesture changed (or one saturated white)
    basis = signature_basis(samples, n_components=24, method=method)
    assert basis.shape == (50, 1) and np.isfinite(basis).all() and not basis.any()
    assert not signatures(back_substitution(basis), samples).any()


def test_signatures_are_unit_and_scale_invariant():
    rng = np.random.default_rng(2)
    basis = rng.normal(size=(300, 6))
    back = back_substitution(basis)
    samples = rng.normal(size=(300, 5))
    sig = signatures(back, samples)
    np.testing.assert_allclose(np.linalg.norm(sig, axis=1), 1.0)
    np.testing.assert_allclose(signatures(back, 3.7 * samples), sig, atol=1e-12)


def _toy_region(n_pixels=400, k=8, n_states=11, seed=3):
    """A region whose two muscles move the sample along two straight paths from neutral (exact states)."""
    rng = np.random.default_rng(seed)
    neutral = rng.normal(size=n_pixels)
    directions = rng.normal(size=(2, n_pixels))
    levels = np.linspace(0, 1, n_states)
    columns = [neutral[:, None] + np.outer(d, levels) for d in directions]
    samples = np.concatenate([neutral[:, None]] + [c[:, 1:] for c in columns], axis=1)
    basis = signature_basis(samples, k, "pca")
    back = back_substitution(basis)
    phis = tuple(signatures(back, c).astype(np.float32) for c in columns)
    mask = np.zeros((20, 20), bool)
    mask.ravel()[:n_pixels] = True
    region = RegionModel("r", mask, ("a", "b"), (n_states, n_states), back.astype(np.float32), phis,
                         np.eye(2), np.ones(2), float(np.median(np.linalg.norm(samples, axis=0))))
    return region, neutral, directions


@pytest.mark.parametrize("muscle", [0, 1])
def test_region_states_interpolate_between_neighbouring_states(muscle):
    region, neutral, directions = _toy_region()
    tables = _RegionTables(region)
    errors = []
    for level in np.linspace(0.13, 0.97, 23):  # mostly between the training states (multiples of 0.1)
        state = classify_region(tables, (neutral + level * directions[muscle]).astype(np.float32))
        assert state.muscle == muscle
        errors.append(abs(state.level - level))
    assert max(errors) < 0.03  # quantised to the states, the error would reach 0.05
    quantised = [abs(round(level * 10) / 10 - level) for level in np.linspace(0.13, 0.97, 23)]
    assert np.mean(errors) < 0.5 * np.mean(quantised)
    assert classify_region(tables, neutral.astype(np.float32)).muscle == -1


def _toy_model(region):
    norm = Normalisation((20, 20))
    crops = np.zeros((region.n_states[0] - 1, 20, 20), np.uint8)
    return MarkerlessModel(("a", "b"), (region,), norm, np.zeros((20, 20), np.float32),
                           {"a": (crops, (0, 0, 20, 20)), "b": (crops + 7, (0, 0, 20, 20))})


def _analyser_of(*regions):
    """An analyser of the toy model with these regions in place of its one."""
    model = _toy_model(regions[0])
    return Analyser(MarkerlessModel(model.muscle_names, regions, model.normalisation, model.neutral_image,
                                    model.gestures))


def test_a_held_region_s_stale_state_counts_only_where_no_region_that_sees_reports_the_muscle():
    from dataclasses import replace

    region, _, _ = _toy_region()
    analyser = _analyser_of(region, replace(region, name="r2"))
    stale, still = RegionState("r", 1, 0.6, 0.1, held=True), RegionState("r2", -1, 0.0, 0.9)
    values, held = analyser.contractions((stale, still))
    assert values[1] == 0.0 and not held.any()  # the region that sees says: at rest
    values, held = analyser.contractions((stale, replace(still, held=True)))
    assert abs(values[1] - 0.3) < 1e-9 and held.all()  # both held: their mean, flagged
    values, held = analyser.contractions((replace(stale, held=False), still))
    assert abs(values[1] - 0.3) < 1e-9 and not held.any()


def test_regions_reporting_one_muscle_combine_by_their_weighted_median():
    """Two regions that see most of muscle "b" read it at 0.9; a third, seeing a fifth of it, at rest (a
    partial view): "b" is 0.9, where their weighted mean would say 0.72."""
    from dataclasses import replace

    region, _, _ = _toy_region()
    analyser = _analyser_of(*(replace(region, name=f"r{i}", weights=np.array([1.0, w]))
                              for i, w in enumerate((0.5, 0.3, 0.2))))
    states = (RegionState("r0", 1, 0.9, 0.9), RegionState("r1", 1, 0.9, 0.9), RegionState("r2", -1, 0.0, 0.9))
    values, held = analyser.contractions(states)
    assert abs(values[1] - 0.9) < 1e-9 and values[0] == 0.0 and not held.any()


def test_no_region_reading_a_muscle_gives_it_zero_not_an_error():
    """The weighted median over no regions at all (a model whose regions list was emptied loaded, then
    indexed an empty cumulative sum): every muscle 0, as for a muscle no region weighs."""
    from livebridge.markerless.analysis import _weighted_median

    np.testing.assert_array_equal(_weighted_median(np.zeros((0, 3)), np.zeros((0, 3))), np.zeros(3))


def test_analyser_holds_lost_and_unrecognised_frames_and_stays_finite():
    region, neutral, directions = _toy_region()
    analyser = Analyser(_toy_model(region), min_confidence=0.3)
    image = np.zeros((20, 20), np.float32)
    image.ravel()[:400] = neutral + 0.6 * directions[1]
    frame = NormalisedFrame(image, image, None, False)
    state, result = analyser.step(AnalysisState(), frame)
    assert result.regions[0].muscle == 1 and abs(result.contractions[1] - 0.6) < 0.03
    assert result.contractions[0] == 0.0 and not result.held.any()
    state, lost = analyser.step(state, NormalisedFrame(image, image, None, True))
    assert lost.held.all() and lost.regions[0].held
    np.testing.assert_allclose(lost.contractions, result.contractions)
    garbage = np.full((20, 20), np.nan, np.float32)
    state, held = analyser.step(state, NormalisedFrame(garbage, garbage, None, False))
    assert held.held.all() and np.isfinite(held.contractions).all()
    np.testing.assert_allclose(held.contractions, result.contractions)
    huge = np.full((20, 20), 1e30, np.float32)
    _, result = analyser.step(state, NormalisedFrame(huge, huge, None, False))
    assert np.isfinite(result.contractions).all() and (0 <= result.contractions).all()
    assert (result.contractions <= 1).all()


def test_model_round_trips_and_bad_files_are_named(tmp_path):
    region, _, _ = _toy_region()
    model = _toy_model(region)
    path = tmp_path / "model.npz"
    model.save(path)
    loaded = MarkerlessModel.load(path)
    assert loaded.muscle_names == model.muscle_names and loaded.image_size == (20, 20)
    np.testing.assert_array_equal(loaded.regions[0].back, region.back)
    np.testing.assert_array_equal(loaded.state_frame("r", "b", 3), np.full((20, 20), 7, np.float32))
    np.testing.assert_array_equal(loaded.state_frame("r", "b", 0), np.zeros((20, 20), np.float32))
    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(InputError, match="not a markerless model") as caught:
        MarkerlessModel.load(tmp_path / "text.npz")
    assert caught.value.path is not None
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(InputError, match="manifest"):
        MarkerlessModel.load(tmp_path / "other.npz")


def test_laplacian_of_the_log_removes_exposure_and_smooth_light():
    rng = np.random.default_rng(4)
    yy, xx = np.mgrid[0:120, 0:160]
    albedo = 0.5 + 0.2 * np.sin(xx / 3.0) * np.cos(yy / 4.0) + 0.05 * rng.normal(size=xx.shape)
    shading = 0.6 + 0.3 * xx / 160  # a light from one side
    image = 200 * albedo * shading
    relit = 0.8 * 200 * albedo * (0.9 - 0.3 * xx / 160)  # 20 % darker, light from the other side
    a, b = lighting_normalise(image), lighting_normalise(relit)
    inner = (slice(4, -4), slice(4, -4))
    assert np.corrcoef(a[inner].ravel(), b[inner].ravel())[0, 1] > 0.995
    plain_a, plain_b = lighting_normalise(image, log=False), lighting_normalise(relit, log=False)
    assert np.abs(a - b)[inner].mean() < 0.3 * np.abs(plain_a - plain_b)[inner].mean() / np.abs(plain_a).mean() \
        * np.abs(a).mean()


def _raised_cosine_take(n_gestures=5, fps=60, rest=0.25, sweep=1.5, noise=0.01, seed=5):
    """Activity of a training take: per gesture, rest, a 0 -> 1 -> 0 raised-cosine sweep, rest."""
    rng = np.random.default_rng(seed)
    block = np.arange(int(round((2 * rest + sweep) * fps))) / fps
    u = np.clip((block - rest) / sweep, 0, 1)
    one = 0.5 - 0.5 * np.cos(2 * np.pi * u)
    strengths = rng.uniform(0.4, 1.0, n_gestures)
    curve = np.concatenate([s * one for s in strengths])
    return curve, curve + noise * np.abs(rng.normal(size=len(curve))), len(block)


def test_bounded_gestures_run_from_first_motion_to_first_maximum():
    truth, activity, block = _raised_cosine_take()
    gestures = find_gestures(activity)
    assert len(gestures) == 5
    for k, g in enumerate(gestures):
        first = k * block + np.flatnonzero(truth[k * block:(k + 1) * block] > 0)[0]
        peak = k * block + int(np.argmax(truth[k * block:(k + 1) * block]))
        assert g.start >= first - 1 and truth[g.start] < 0.06  # first motion clear of the noise (0.01)
        assert peak - 6 <= g.peak <= peak  # within the peak tolerance, never after the first maximum
        assert truth[g.peak] >= 0.95 * truth[peak]
        assert g.start < g.peak < g.end < (k + 1) * block


def test_a_saturating_activity_s_gesture_peaks_where_the_broader_activity_does():
    """The few most changed pixels stop changing before a large gesture is full (a jaw's at 0.8 of its
    opening here): the bounded gesture then ends where a broader activity, still growing, peaks."""
    truth, broad, block = _raised_cosine_take()
    strength = np.array([truth[k * block:(k + 1) * block].max() for k in range(5)]).repeat(block)
    saturated = np.minimum(broad, 0.8 * strength)
    early = find_gestures(saturated)
    found = find_gestures(saturated, breadth=broad)
    assert len(early) == len(found) == 5
    for k, (e, g) in enumerate(zip(early, found)):
        peak = k * block + int(np.argmax(truth[k * block:(k + 1) * block]))
        assert truth[e.peak] < 0.85 * truth[peak]
        assert peak - 6 <= g.peak <= peak and truth[g.peak] >= 0.95 * truth[peak]
        assert (g.start, g.end) == (e.start, e.end)


def _motion(truth: np.ndarray, noise: float, seed: int) -> np.ndarray:
    """A motion curve of ``truth``: its central difference's size plus noise, NaN at the ends."""
    motion = np.full(len(truth), np.nan)
    motion[1:-1] = np.abs(truth[2:] - truth[:-2])
    return motion + noise * np.abs(np.random.default_rng(seed).normal(size=len(truth)))


def test_a_gesture_whose_activities_both_saturate_peaks_where_the_face_stops_moving():
    """15 fps, both activities within 3 % of their tops two frames before the maximum (an opening jaw's
    broader activity, 0.92 of its opening): the motion between frames places the peak."""
    truth, _, block = _raised_cosine_take(fps=15)
    strength = np.array([truth[k * block:(k + 1) * block].max() for k in range(5)]).repeat(block)
    rng = np.random.default_rng(8)
    noisy = [np.minimum(truth, c * strength) + 0.002 * np.abs(rng.normal(size=len(truth))) for c in (0.8, 0.92)]
    without = find_gestures(noisy[0], breadth=noisy[1])
    found = find_gestures(noisy[0], breadth=noisy[1], motion=_motion(truth, 0.003, 9))
    assert len(without) == len(found) == 5
    for k, (w, g) in enumerate(zip(without, found)):
        peak = k * block + int(np.argmax(truth[k * block:(k + 1) * block]))
        assert w.peak <= peak - 2  # the activities alone end it early
        assert abs(g.peak - peak) <= 1 and truth[g.peak] >= 0.95 * truth[peak]
        assert (g.start, g.end) == (w.start, w.end)


def test_a_held_expression_peaks_at_the_hold_s_first_frames():
    """A hold at full actuation: the peak is where the face stopped, not any of the still frames after it."""
    rise = 0.5 - 0.5 * np.cos(np.pi * np.linspace(0, 1, 20))
    gesture = np.concatenate([np.zeros(20), rise, np.ones(40), rise[::-1], np.zeros(20)])
    truth = np.tile(gesture, 3)
    rng = np.random.default_rng(3)
    activity = truth + 0.005 * np.abs(rng.normal(size=len(truth)))
    found = find_gestures(activity, motion=_motion(truth, 0.01, 4))
    assert len(found) == 3
    for k, g in enumerate(found):
        hold = k * len(gesture) + 39  # the rise's last frame, at full actuation
        assert hold - 1 <= g.peak <= hold + 2, (g.peak, hold)


def test_motion_is_the_change_between_a_frame_s_neighbours_and_unknown_beside_a_lost_frame():
    """A bright square moving 2 px a frame, then holding: the motion falls to nothing where it stops; NaN at the
    take's ends and next to a frame whose LEDs were lost."""
    frames = np.zeros((12, 40, 60), np.uint8)
    for t in range(12):
        x = 10 + 2 * min(t, 6)
        frames[t, 15:25, x:x + 10] = 200
    lost = np.zeros(12, bool)
    lost[9] = True
    motion = change_curves(frames, lost, motion_top=0.05)[1]
    assert np.isnan(motion[[0, 8, 10, 11]]).all() and np.isfinite(motion[1:8]).all()
    assert (motion[1:6] > 10).all()  # moving: the square's edges changed
    assert motion[7] == 0.0  # frames 6 and 8 are the same: the hold


def test_gestures_with_lost_frames_and_none_at_all():
    _, activity, block = _raised_cosine_take(n_gestures=3)
    activity = activity.copy()
    activity[block + 10: block + 14] = np.nan  # LEDs lost during the second gesture's onset
    assert len(find_gestures(activity)) == 3
    rng = np.random.default_rng(6)
    assert find_gestures(0.01 * np.abs(rng.normal(size=500))) == []
    assert find_gestures(np.full(10, np.nan)) == []
    assert find_gestures(activity, GestureConfig(detect_k=1e6)) == []


def test_co_articulation_regions_are_intersections_with_small_ones_merged():
    rois = np.zeros((3, 60, 80), bool)
    rois[0, 5:35, 5:45] = True  # muscle 0
    rois[1, 20:50, 30:70] = True  # muscle 1 overlaps muscle 0
    rois[2, 52:58, 5:8] = True  # muscle 2: a tiny region alone, dropped as an island
    rois[2, 5:8, 60:63] = True
    regions = co_articulation_regions(rois, RegionConfig(min_area=0.01))
    muscle_sets = sorted(r.muscles for r in regions)
    assert muscle_sets == [(0,), (0, 1), (1,)]
    both = next(r for r in regions if r.muscles == (0, 1))
    assert both.mask.sum() == 15 * 15 and both.mask[20:35, 30:45].all()
    union = np.any([r.mask for r in regions], axis=0)
    assert not np.any(np.sum([r.mask for r in regions], axis=0) > 1)
    assert union.sum() == (rois[0] | rois[1]).sum()
    merged = co_articulation_regions(rois, RegionConfig(min_area=0.15))  # the overlap is under 15 %
    assert len(merged) == 2  # merged into a neighbour, where muscle 1 covers under min_cover: not kept there
    assert sorted(r.muscles for r in merged) == [(0,), (1,)]
    assert sorted(r.muscles for r in co_articulation_regions(rois, RegionConfig(min_area=0.15, min_cover=0.1))) \
        in ([(0,), (0, 1)], [(0, 1), (1,)])
    assert len(co_articulation_regions(rois, RegionConfig(min_area=0.0, max_regions=2))) == 2
