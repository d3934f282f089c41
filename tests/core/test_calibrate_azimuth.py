"""The albedo calibration's relative-azimuth nodes (addon.core.neural.calibrate: AZIMUTHS, solve_azimuth)."""

import numpy as np

from addon.core import kernels
from addon.core.neural import calibrate as cal

K, P = len(cal.COSINES), cal.AZIMUTHS


def _unit_rows(rng, n):
    v = np.c_[rng.normal(size=(n, 2)), rng.uniform(0.0, 1.0, n)]
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _table(rng):
    t = rng.uniform(0.3, 3.0, size=(K, K, P, 3))
    return (t + t.transpose(1, 0, 2, 3)) / 2


def test_the_factor_is_the_hats_of_both_cosines_and_the_azimuth_and_reciprocal():
    """The compiled lookup (``kernels.scale_by_table``) against the numpy hat functions the solve bins with."""
    rng = np.random.default_rng(5)
    grid = np.asarray(cal.COSINES)
    n = 500
    x, y, c = rng.uniform(0, 1, n), rng.uniform(0, 1, n), rng.uniform(-1, 1, n)
    c[:5] = (1.0, -1.0, 0.0, 0.5, -0.5)  # on and between the nodes
    table = _table(rng)
    calib = cal.AlbedoCalibration(grid, np.ones((K, 3)), table, *(np.ones((K, 3)),) * 4)
    want = np.einsum("nk,nl,np,klpc->nc", cal._hats(x, grid), cal._hats(y, grid), cal.azimuth_hats(c), table)
    np.testing.assert_allclose(calib.factor(x, y, c), want, rtol=1e-12)
    np.testing.assert_allclose(calib.factor(x, y, c), calib.factor(y, x, c), rtol=1e-12)  # reciprocal


def test_the_renderers_loop_applies_the_same_factor_as_apply_and_keeps_f_non_negative():
    """``kernels.decoded_brdf`` (the render) and ``RowCalibration.apply`` (numpy callers) read the relative azimuth
    alike; swapping wi and wo changes nothing; f stays >= 0."""
    from addon.core.neural import top_lobe

    rng = np.random.default_rng(8)
    n = 3000
    wi, wo = _unit_rows(rng, n), _unit_rows(rng, n)
    rows = cal.RowCalibration(np.asarray(cal.COSINES), np.stack([_table(rng) for _ in range(2)]), rng.integers(0, 2, n))
    decoded = rng.random((n, 3)).astype(np.float32)
    want = rows.apply(decoded, wi, wo)
    got = decoded.copy()
    kernels.decoded_brdf(
        got,
        wi,
        wo,
        rows.arrays(),
        top_lobe.NO_TOP_ROWS,
        top_lobe.transmittance_grids(),
        False,
        False,
        kernels.EVERY_ROW,
    )
    np.testing.assert_allclose(got, want, rtol=2e-6)
    np.testing.assert_allclose(rows.apply(decoded, wo, wi), want, rtol=1e-6)
    assert (want >= 0).all()
    # an azimuth-free table (one node) is the elevation table it was: no azimuth read
    flat = cal.RowCalibration(rows.cosines, rows.tables[:, :, :, :1], rows.which)
    elevation = cal.RowCalibration(rows.cosines, rows.tables[:, :, :, 0], rows.which)
    np.testing.assert_allclose(flat.apply(decoded, wi, wo), elevation.apply(decoded, wi, wo), rtol=1e-12)


def _moments(rng, samples=20000):
    """Decoded moments of a made-up lobe from samples: cosines uniform, relative azimuths uniform."""
    k = K
    cos_i = rng.uniform(0.0, 1.0, (k, samples))
    cos_phi = np.cos(rng.uniform(0.0, np.pi, (k, samples)))
    v = rng.uniform(0.5, 1.5, (k, samples, 3))
    grid = np.asarray(cal.COSINES)
    cells, weights = cal.exit_cells(cos_i.reshape(-1), cos_phi.reshape(-1), grid)
    b = k * P
    angle = np.repeat(np.arange(k), samples)
    flat = ((angle[:, None, None] * b + cells[:, :, None]) * b + cells[:, None, :]).reshape(-1)
    both = (weights[:, :, None] * weights[:, None, :]).reshape(len(flat) // 16, -1)
    az = cal._binned(flat, both, v.reshape(-1, 3), k * b * b).reshape(k, k, P, k, P, 3) / samples
    return cal.DecodedMoments(az.sum(axis=(2, 4)), np.zeros((k, k, 3)), az, np.zeros((k, k, P, 3)))


def test_a_lobe_wrong_in_azimuth_only_gets_its_same_and_opposite_side_energies_corrected():
    """The reference sends more of every angle's light forward (towards the mirror direction, phi = pi) and less
    back (phi = 0) than the decoded lobe, at the same elevations: an elevation-only table cannot change that (its
    energies per azimuth bin keep the decoded split), the azimuth nodes bring both sides to the reference's."""
    rng = np.random.default_rng(3)
    moments = _moments(rng)
    truth = np.ones((K, K, P, 3))
    truth[1:, 1:] *= np.linspace(0.6, 1.5, P)[None, None, :, None]  # back 0.6x, forward 1.5x; none at the normal
    target = cal.azimuth_energy(moments.azimuth_pairs, truth)
    elevation = cal.solve_table(moments, np.ones((K, 3)), target.sum(axis=2), 1e-6 * target.sum(axis=2) + 1e-9)
    old = cal.azimuth_energy(moments.azimuth_pairs, np.repeat(elevation[:, :, None], P, axis=2))
    new = cal.azimuth_energy(moments.azimuth_pairs, cal.solve_azimuth(moments, elevation, target, 1e-4 * target))
    back, forward = (slice(2, None), slice(1, None), 0), (slice(2, None), slice(1, None), P - 1)
    for got, ok in ((old, False), (new, True)):
        ratio_back, ratio_forward = got[back].sum() / target[back].sum(), got[forward].sum() / target[forward].sum()
        assert (abs(ratio_back - 1) < 0.03 and abs(ratio_forward - 1) < 0.03) == ok, (ratio_back, ratio_forward)
    np.testing.assert_allclose(new.sum(axis=2), target.sum(axis=2), rtol=0.03)


def test_a_reference_within_its_noise_keeps_the_elevation_table():
    rng = np.random.default_rng(4)
    moments = _moments(rng, 4000)
    elevation = np.clip(_table(rng)[:, :, 0], 0.5, 2.0)
    target = cal.azimuth_energy(moments.azimuth_pairs, np.repeat(elevation[:, :, None], P, axis=2))
    noisy = target * rng.uniform(0.95, 1.05, target.shape)
    got = cal.solve_azimuth(moments, elevation, noisy, 0.2 * target + 1e-9)
    np.testing.assert_allclose(got, np.repeat(elevation[:, :, None], P, axis=2), rtol=1e-9)
    np.testing.assert_array_equal(got, got.transpose(1, 0, 2, 3))


def _parts(albedo, albedo_se, bins, bins_se):
    """Reference parts of a coating-free material: every part is the whole (``cal.ReferenceParts``)."""
    elevation, elevation_se = bins.sum(axis=2), np.sqrt((bins_se**2).sum(axis=2))
    return cal.ReferenceParts(
        albedo, albedo_se, albedo, albedo_se, elevation, elevation_se, elevation, elevation_se,
        bins, bins_se, bins, bins_se,
    )  # fmt: skip


def test_an_azimuth_fit_keeps_each_angles_albedo_where_one_side_is_within_the_noise_bin_by_bin():
    """The reference sends 1.4x the decoded light forward and 0.6x back at every angle, its albedo the decoded one;
    the forward bins are clear of the noise, the backscatter bins each within it (their gaps together are not). A fit
    to the bins alone raised the forward light and left the back, 8-10% over the albedo: ``_solve`` kept the
    elevation table. With each angle's albedo as a row too, the fit lowers the back and keeps the azimuth nodes."""
    rng = np.random.default_rng(12)
    moments = _moments(rng)
    truth = np.ones((K, K, P, 3))
    truth[1:, 1:] *= np.array([0.6, 1.0, 1.4])[None, None, :, None]  # none at the normal
    target = cal.azimuth_energy(moments.azimuth_pairs, truth)
    bins_se = 1e-3 * target
    bins_se[:, :, 0] = target[:, :, 0]  # backscatter: each bin within its noise
    albedo = target.sum(axis=(1, 2))
    c = cal._solve(_parts(albedo, 1e-3 * albedo, target, bins_se), moments, np.zeros(K), remainder=False)
    energy = cal.azimuth_energy(moments.azimuth_pairs, c.table)
    np.testing.assert_allclose(energy.sum(axis=(1, 2)), albedo, rtol=0.01)
    np.testing.assert_allclose(c.calibrated, albedo, rtol=0.01)
    back, forward = c.table[2:, 2:, 0], c.table[2:, 2:, P - 1]
    assert np.median(forward / back) > 1.8, np.median(forward / back)  # 1.4 / 0.6 = 2.3: not the elevation table
    forward_energy = energy[2:, 1:, P - 1].sum() / target[2:, 1:, P - 1].sum()
    assert abs(forward_energy - 1) < 0.03, forward_energy


def test_the_reference_bins_exit_directions_sparsely_as_the_dense_weights_say():
    """``calibrate.exit_bin_cells`` (what the walks are binned by) is ``exit_bins`` (the top lobe's and the dense
    weights') in its sparse form: distinct cells, weights summing to one per kind."""
    rng = np.random.default_rng(2)
    wi = _unit_rows(rng, 2000)
    wi[:3] = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (-0.6, 0.0, 0.8))  # along the normal, at the horizon, backwards
    cells, weights = cal.exit_bin_cells(wi)
    dense = cal.exit_bins(wi)
    assert dense.shape == (len(wi), cal.EXIT_BINS)
    assert (np.diff(np.sort(cells, axis=1), axis=1) > 0).all()
    np.testing.assert_allclose(np.take_along_axis(dense, cells, axis=1), weights, rtol=0, atol=0)
    np.testing.assert_allclose(dense[:, :K].sum(axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(dense[:, K:].sum(axis=1), 1.0, rtol=1e-12)
