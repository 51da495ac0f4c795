"""The 2.5D particle filter: likelihood against a direct oracle, resampling, convergence."""

from __future__ import annotations

import numpy as np
import pytest

from fusion_server.grid import FloorMaps, VoxelGrid
from fusion_server.particle_filter import (
    ParticleFilter,
    box_count,
    effective_sample_size,
    floor_evidence,
    likelihood,
    propagate,
    systematic_resample,
)

GRID = VoxelGrid.from_bounds((0.0, 0.0, 0.0), (4.0, 3.0, 2.0), 0.05)  # 80 x 60 floor cells
NY, NX = GRID.shape[1], GRID.shape[0]
FPS_NS = 1_000_000_000 // 15


def floor(count: np.ndarray) -> FloorMaps:
    return FloorMaps(count=count.astype(np.int32), top_m=(count * GRID.voxel_m).astype(np.float32))


def square_person(cx_m: float, cy_m: float, half_m: float = 0.2, height_vox: int = 30) -> np.ndarray:
    """Count map of a square footprint of columns ``height_vox`` voxels high."""
    count = np.zeros((NY, NX), dtype=np.int32)
    x = (np.arange(NX) + 0.5) * GRID.voxel_m
    y = (np.arange(NY) + 0.5) * GRID.voxel_m
    inside = (np.abs(y[:, None] - cy_m) < half_m) & (np.abs(x[None, :] - cx_m) < half_m)
    count[inside] = height_vox
    return count


def oracle_likelihood(count: np.ndarray, x_m: float, y_m: float, alpha_m: float, k_m: float, pad: int) -> float:
    """Equation (5) by explicit slicing of a zero-padded map."""
    v = GRID.voxel_m
    p = np.zeros((NY + 2 * pad, NX + 2 * pad), dtype=np.int64)
    p[pad : pad + NY, pad : pad + NX] = count
    i = int(np.clip(np.floor(x_m / v), 0, NX - 1)) + pad
    j = int(np.clip(np.floor(y_m / v), 0, NY - 1)) + pad
    k = max(1, round(k_m / v))
    a = int(np.clip(round(alpha_m / v), k, pad - 1 - k))
    inner = p[j - (a - k) : j + (a - k) + 1, i - (a - k) : i + (a - k) + 1]
    outer = p[j - (a + k) : j + (a + k) + 1, i - (a + k) : i + (a + k) + 1]
    h = inner.max()
    if h == 0:
        return 0.0
    n_in, n_out = inner.sum(), outer.sum()
    f_in = n_in / (h * inner.size)
    f_d = (n_out / outer.size - n_in / inner.size) / (2 * k * h)
    return max(0.0, -(f_in**2) * np.sqrt(n_out) * f_d)


def test_likelihood_hand_worked_value():
    # A 5 x 5 cell block 10 voxels high; particle on its centre cell with
    # alpha = 3 cells and k = 1 cell: inner box 5 x 5 = the block, outer 9 x 9.
    count = np.zeros((NY, NX), dtype=np.int32)
    count[20:25, 30:35] = 10
    ev = floor_evidence(floor(count), GRID, max_half_m=0.7)
    x, y = (32 + 0.5) * 0.05, (22 + 0.5) * 0.05
    lik = likelihood(np.array([[x, y, 0.15]]), ev, k_m=0.05)
    # F(a-k) = 250 / (10 * 25) = 1; Fd = (250/81 - 250/25) / (2 * 1 * 10); N(a+k) = 250.
    expected = -1.0 * np.sqrt(250.0) * ((250 / 81 - 250 / 25) / 20.0)
    assert lik[0] == pytest.approx(expected, rel=1e-12)
    assert box_count(np.array([[x, y, 0.15]]), ev)[0] == 250
    assert box_count(np.array([[x, y, 0.05]]), ev)[0] == 90


def test_likelihood_equals_direct_oracle_on_random_maps():
    rng = np.random.default_rng(11)
    for _ in range(5):
        count = (rng.integers(1, 40, size=(NY, NX)) * (rng.random((NY, NX)) < 0.25)).astype(np.int32)
        ev = floor_evidence(floor(count), GRID, max_half_m=0.7)
        particles = np.stack(
            [rng.uniform(-0.3, 4.3, 300), rng.uniform(-0.3, 3.3, 300), rng.uniform(0.0, 0.8, 300)], axis=1
        )
        for k_m in (0.05, 0.1, 0.15):
            got = likelihood(particles, ev, k_m=k_m)
            want = [oracle_likelihood(count, *p, k_m, ev.pad) for p in particles]
            np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_likelihood_is_zero_on_empty_floor():
    ev = floor_evidence(floor(np.zeros((NY, NX))), GRID, max_half_m=0.7)
    assert np.all(likelihood(np.array([[1.0, 1.0, 0.2], [5.0, -1.0, 0.4]]), ev, k_m=0.1) == 0)


def test_likelihood_peaks_on_the_person_not_between_two():
    count = square_person(1.5, 1.5) + square_person(2.1, 1.5)  # 0.6 m apart, 0.2 m gap
    ev = floor_evidence(floor(count), GRID, max_half_m=0.7)
    xs = np.arange(1.2, 2.41, 0.025)
    best = []
    for x in xs:
        alphas = np.arange(0.15, 0.61, 0.05)
        best.append(likelihood(np.stack([np.full_like(alphas, x), np.full_like(alphas, 1.5), alphas], 1), ev, k_m=0.1).max())
    best = np.array(best)
    mid = np.argmin(np.abs(xs - 1.8))
    assert best[mid] < 0.2 * best.max()
    left = xs[np.argmax(np.where(xs < 1.8, best, -1))]
    right = xs[np.argmax(np.where(xs > 1.8, best, -1))]
    assert abs(left - 1.5) <= 0.1 and abs(right - 2.1) <= 0.1


def test_systematic_resample_counts_are_within_one_of_expected():
    rng = np.random.default_rng(5)
    for _ in range(50):
        w = rng.random(37) ** 3
        w /= w.sum()
        idx = systematic_resample(w, rng)
        assert idx.shape == (37,) and idx.dtype == np.intp
        counts = np.bincount(idx, minlength=37)
        assert np.all(counts >= np.floor(37 * w) - 1e-9) and np.all(counts <= np.ceil(37 * w) + 1e-9)
        assert np.all(np.diff(idx) >= 0)


def test_systematic_resample_hand_worked():
    # Pointers (u + [0, 1, 2, 3]) / 4 with u = the generator's first draw.
    u = np.random.default_rng(9).random()
    w = np.array([0.5, 0.25, 0.0, 0.25])
    idx = systematic_resample(w, np.random.default_rng(9))
    want = np.searchsorted(np.cumsum(w), (u + np.arange(4)) / 4, side="right")
    assert idx.tolist() == want.tolist()
    assert np.bincount(idx, minlength=4).tolist() == [2, 1, 0, 1]


def test_effective_sample_size():
    assert effective_sample_size(np.full(10, 0.1)) == pytest.approx(10.0)
    assert effective_sample_size(np.eye(1, 10)[0]) == pytest.approx(1.0)


def test_propagate_statistics_and_limits():
    particles = np.tile([1.0, 2.0, 0.3], (20000, 1))
    before = particles.copy()
    out = propagate(
        particles, 0.25, velocity_mps=(1.0, -2.0), position_noise_m=0.4, alpha_noise_m=0.2,
        alpha_range_m=(0.2, 0.35), rng=np.random.default_rng(1),
    )
    assert np.array_equal(particles, before)
    assert out[:, 0].mean() == pytest.approx(1.25, abs=0.01)
    assert out[:, 1].mean() == pytest.approx(1.5, abs=0.01)
    assert out[:, 0].std() == pytest.approx(0.4 * 0.5, rel=0.03)
    assert out[:, 2].min() >= 0.2 and out[:, 2].max() <= 0.35
    assert np.array_equal(
        propagate(particles, 0.0, position_noise_m=1.0, alpha_noise_m=1.0, alpha_range_m=(0.1, 1.0), rng=np.random.default_rng(1)),
        particles,
    )


def run_filter(seed: int, truth_xy=(2.3, 1.7), start_xy=(2.1, 1.85), steps: int = 15) -> tuple[ParticleFilter, list[np.ndarray]]:
    ev = floor_evidence(floor(square_person(*truth_xy)), GRID, max_half_m=0.7)
    pf = ParticleFilter(*start_xy, 0.2, rng=np.random.default_rng(seed))
    return pf, [pf.step(ev, n * FPS_NS) for n in range(steps)]


def test_filter_converges_to_a_still_person():
    # Start 0.25 m off; within 15 frames (1 s at 15 fps) the estimate is within 3 cm.
    for seed in range(5):
        pf, estimates = run_filter(seed)
        err = np.hypot(estimates[-1][0] - 2.3, estimates[-1][1] - 1.7)
        assert err < 0.03, (seed, err)
        assert pf.supported
        assert 0.15 <= estimates[-1][2] <= 0.3


def test_filter_is_deterministic_for_a_seed():
    pf_a, est_a = run_filter(42)
    pf_b, est_b = run_filter(42)
    assert np.array_equal(pf_a.particles, pf_b.particles)
    assert np.array_equal(np.array(est_a), np.array(est_b))
    pf_c, _ = run_filter(43)
    assert not np.array_equal(pf_a.particles, pf_c.particles)


def test_filter_follows_a_walking_person():
    # 1.2 m/s along x for 2 s; the filter is given the walking velocity as drift.
    pf = ParticleFilter(1.0, 1.5, 0.2, rng=np.random.default_rng(3))
    for n in range(30):
        x = 1.0 + 1.2 * n / 15
        ev = floor_evidence(floor(square_person(x, 1.5)), GRID, max_half_m=0.7)
        est = pf.step(ev, n * FPS_NS, velocity_mps=(1.2, 0.0))
        assert np.hypot(est[0] - x, est[1] - 1.5) < 0.05, n


def test_filter_without_evidence_keeps_weights_and_reports_unsupported():
    ev = floor_evidence(floor(np.zeros((NY, NX))), GRID, max_half_m=0.7)
    pf = ParticleFilter(1.0, 1.0, 0.2, rng=np.random.default_rng(0), resample_below=0.0)
    pf.step(ev, 0)
    assert not pf.supported
    np.testing.assert_allclose(pf.weights, 1.0 / 200)


def test_filter_time_step_comes_from_stamps():
    ev = floor_evidence(floor(np.zeros((NY, NX))), GRID, max_half_m=0.7)
    pf = ParticleFilter(1.0, 1.0, 0.2, rng=np.random.default_rng(0), init_spread_m=0.0, position_noise_m=0.0, alpha_noise_m=0.0)
    pf.step(ev, 1_000_000_000)
    pf.step(ev, 1_500_000_000, velocity_mps=(0.4, -0.2))  # 0.5 s later
    np.testing.assert_allclose(pf.estimate()[:2], [1.2, 0.9])
    with pytest.raises(ValueError, match="stamp_ns"):
        pf.step(ev, 1_400_000_000)
    pf.step(ev, 11_500_000_000, velocity_mps=(1.0, 0.0))  # a 10 s gap counts as max_dt_s = 0.5 s
    np.testing.assert_allclose(pf.estimate()[:2], [1.7, 0.9])


def test_evidence_must_cover_the_filter_boxes():
    ev = floor_evidence(floor(np.zeros((NY, NX))), GRID, max_half_m=0.3)
    pf = ParticleFilter(1.0, 1.0, 0.2, rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="evidence"):
        pf.step(ev, 0)


@pytest.mark.parametrize(
    "bad",
    [
        {"n_particles": 0},
        {"k_m": 0.0},
        {"alpha_range_m": (0.5, 0.2)},
        {"position_noise_m": -1.0},
        {"resample_below": 1.5},
        {"max_dt_s": 0.0},
        {"rng": 7},
    ],
)
def test_bad_filter_settings_name_themselves(bad):
    kwargs = {"rng": np.random.default_rng(0), **bad}
    with pytest.raises(ValueError, match=next(iter(bad))):
        ParticleFilter(1.0, 1.0, 0.2, **kwargs)


def test_floor_evidence_checks_shape():
    with pytest.raises(ValueError, match="count"):
        floor_evidence(FloorMaps(count=np.zeros((3, 3), np.int32), top_m=np.zeros((3, 3), np.float32)), GRID, max_half_m=0.5)
