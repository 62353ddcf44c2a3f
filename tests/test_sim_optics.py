"""The simulator's optical models against independent formulas, and the decoder's passive
compensation against the response that made the images (small images)."""

from __future__ import annotations

import numpy as np
import pytest
from scancell.analysis.phase import DecodeSettings, decode_phase
from scancell.analysis.phase_response import equivalent_gamma, error_table, folded_histogram
from scancell.model.patterns import FringeSequence
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.host import check_options
from scancell.sim.optics_profile import (
    REALISTIC,
    ProfileError,
    defocus_px_per_unit,
    optics_profile,
    response_harmonics,
)
from scancell.sim.render_kernels import pattern_dn, sensor_dn, surface_terms

pytestmark = pytest.mark.unit


def test_sensor_noise_follows_emva_1288():
    """Mean and variance in DN against the EMVA 1288 linear model written out here:
    μ_y = K μ_e, σ_y² = K² (σ_d² + μ_e) + 1/12 (quantisation), K = 255 / full well."""
    p = REALISTIC
    K = 255.0 / p.full_well_e
    rng = np.random.default_rng(1)
    for mean_dn in (20.3, 60.0, 180.0):  # σ ≥ 0.7 DN: the 1/12 quantisation term holds
        dn = np.full((400, 500), mean_dn, np.float32)
        img = sensor_dn(dn, rng.standard_normal(dn.shape, np.float32), K, p.dark_noise_e, 0.0)
        mu_e = mean_dn / K
        expected_var = K**2 * (p.dark_noise_e**2 + mu_e) + 1 / 12
        assert img.mean() == pytest.approx(mean_dn, abs=0.05)
        assert img.astype(float).var() == pytest.approx(expected_var, rel=0.08)
    # saturation: a signal above the full well reads 255, never wraps
    hot = sensor_dn(np.full((10, 10), 400.0, np.float32), np.zeros((10, 10), np.float32), K,
                    p.dark_noise_e, 0.0)
    assert (hot == 255).all()


def test_defocus_blur_against_the_thin_lens_image_distances():
    """Blur circle from the image distances v = 1/(1/f − 1/d): c = A · |v_d − v_s| / v_d."""
    f_px, pitch, N, s = 4637.7, 0.00345, 8.0, 650.0
    f = f_px * pitch
    d = np.array([400.0, 550.0, 650.0, 800.0, 1100.0])
    v_s = 1 / (1 / f - 1 / s)
    v_d = 1 / (1 / f - 1 / d)
    c_mm = (f / N) * np.abs(v_d - v_s) / v_d
    k = defocus_px_per_unit(f_px, pitch, N, s)
    n = len(d)
    lit = np.zeros(n)  # the renderer's kernel: the projector's blur at d, the camera's at d
    one = np.ones(n, np.float32)
    _, _, sigma_p, sigma_c = surface_terms(lit, one, d.astype(np.float32), d.astype(np.float32),
                                           one, one, 1.0, 0.1, 650.0, k, s, k, s, 0.0, 1.0)
    np.testing.assert_allclose(sigma_p, c_mm / pitch / 4, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(sigma_c, c_mm / pitch / 4, rtol=1e-5, atol=1e-6)
    assert defocus_px_per_unit(f_px, pitch, float("inf"), s) == 0


@pytest.mark.parametrize("gamma", [1.0, 2.2])
def test_response_harmonics_rebuild_the_projected_light(gamma):
    """Σ c_k cos kθ against the response applied to the 8-bit pattern directly."""
    p = optics_profile("realistic", projector_gamma=gamma)
    c = response_harmonics(p, 0.5, 0.5, harmonics=40)
    theta = np.linspace(0, 2 * np.pi, 721)
    direct = p.projector_light(np.rint((0.5 + 0.5 * np.cos(theta)) * 255) / 255)
    rebuilt = sum(ck * np.cos(k * theta) for k, ck in enumerate(c))
    assert np.abs(rebuilt - direct).max() < 0.01
    # pre-compensation by the inverse response makes the light linear again
    inverse = np.rint(255 * (np.arange(256) / 255) ** (1 / gamma)).astype(int)
    lin = response_harmonics(p, 0.5, 0.5, inverse)
    assert np.abs(lin[2:]).max() < 0.01 and lin[1] == pytest.approx(0.5, abs=0.01)


def test_projector_defocus_damps_the_fringe_like_a_gaussian_blur():
    """The kernel's harmonic damping against a numerical convolution of the light profile."""
    p = optics_profile("realistic")
    coeffs = response_harmonics(p, 0.5, 0.5)
    nu, sigma = 64 / 1280, 3.0
    x = np.arange(0, 400, 0.25)
    light = sum(ck * np.cos(2 * np.pi * k * nu * x) for k, ck in enumerate(coeffs))
    kern_x = np.arange(-25, 25.01, 0.25)
    kern = np.exp(-0.5 * (kern_x / sigma) ** 2)
    blurred = np.convolve(light, kern / kern.sum(), mode="same")
    proj_x = x[None, :].astype(np.float64)
    ones = np.ones_like(proj_x, np.float32)
    out = pattern_dn(0 * ones, ones, proj_x, sigma * ones, True, nu, 0.0, coeffs, 0.0, 1.0)
    inner = slice(200, -200)
    assert np.abs(out[0, inner] - blurred[inner]).max() < 2e-3


@pytest.fixture(scope="module")
def realistic_cell() -> SimCell:
    cell = SimCell(SimCellConfig(camera_scale=8, optics=optics_profile("realistic"), seed=4))
    cell.move_joints(cell.start_joints())
    cell.load_sequence(FringeSequence())
    return cell


def test_paints_highlights_and_plate(realistic_cell):
    """Dark body paint, light bumper, bright plate; highlights saturate where the specular lobe
    dominates, never on the matte plate."""
    from scancell.sim import parts

    cell = realistic_cell
    white = cell.render("left", -2)
    g = cell.geometry("left")
    dirs = cell._pixel_rays("left").reshape(-1, 3)
    T = cell.T_world_from_camera("left")
    hits = cell.scene.cast(T[:3, 3], dirs @ T[:3, :3].T.astype(np.float32))
    obj = cell.scene.get("car_rear")
    region = np.full(hits.t.shape, -1)
    on_part = hits.object_index == cell.scene.objects.index(obj)
    region[on_part] = obj.regions[hits.primitive[on_part]]
    region = region.reshape(white.shape)
    lit = np.isfinite(g.proj_x)
    med = {r: np.median(white[lit & (region == r)]) for r in
           (parts.REGION_BODY, parts.REGION_BUMPER, parts.REGION_PLATE)}
    assert med[parts.REGION_BODY] < med[parts.REGION_BUMPER] < med[parts.REGION_PLATE]
    assert (white[lit & (region == parts.REGION_BODY)] >= 255).any(), "no highlight saturates"
    assert not (white[lit & (region == parts.REGION_PLATE)] >= 255).mean() > 0.5


def test_passive_compensation_recovers_the_response_that_made_the_images():
    """gamma 2.2 projector, ideal otherwise: compensation keeps the linear decode's pixels and
    names the gamma; without it most are lost."""
    seq = FringeSequence()
    decoded = {}
    for gamma in (1.0, 2.2):
        cell = SimCell(SimCellConfig(camera_scale=4, part="flat", seed=2,
                                     optics=optics_profile("ideal", projector_gamma=gamma)))
        cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(
            cell.cfg.T_world_from_part[:3, 3], 600.0)))
        cell.load_sequence(seq)
        imgs = cell.render_sequence("left")
        truth = cell.geometry("left").proj_x
        for comp in ("off", "passive"):
            pm = decode_phase(imgs, seq, 1280, DecodeSettings(compensation=comp))
            err = np.abs(pm.column - truth)[pm.valid]
            decoded[gamma, comp] = (pm.valid.sum(), np.sqrt(np.mean(err**2)), pm.response)
    n_linear = decoded[1.0, "passive"][0]
    assert decoded[2.2, "off"][0] < 0.5 * n_linear
    n, rms, response = decoded[2.2, "passive"]
    assert n >= 0.97 * n_linear
    assert rms < 0.1, f"column RMS {rms} px"
    assert response["equivalent_gamma"] == pytest.approx(2.2, abs=0.1)
    assert response["compensated"] and not response["linear"]
    assert decoded[1.0, "passive"][2]["linear"]


def test_error_table_of_a_known_distortion():
    """A synthetic folded-phase distortion φ' = φ + a sin 3φ is found back from its histogram."""
    rng = np.random.default_rng(0)
    phi = rng.uniform(0, 2 * np.pi, 400_000)
    measured = np.mod(phi + 0.1 * np.sin(3 * phi), 2 * np.pi)
    table = error_table(folded_histogram(measured, np.ones(phi.size, bool), 3), 3)
    u = np.arange(table.size) * (2 * np.pi / 3) / (table.size - 1)
    # the error as a function of the measured phase: solve u = φ + 0.1 sin 3φ for φ
    true_phi = u.copy()
    for _ in range(50):
        true_phi = u - 0.1 * np.sin(3 * true_phi)
    assert np.abs(table - (u - true_phi)).max() < 0.01
    assert np.isfinite(equivalent_gamma(table[None], 3))


def test_profiles_and_effects_are_checked():
    with pytest.raises(ProfileError, match="unknown optics profile 'shiny'"):
        optics_profile("shiny")
    with pytest.raises(ProfileError, match="unknown optics effect 'glare'"):
        optics_profile("realistic", ["glare"])
    off = optics_profile("realistic", ["projector_response", "paints"])
    assert off.projector_gamma == 1.0 and off.paints == "uniform"
    assert off.sensor_model == "emva"
    assert check_options({"profile": "realistic", "effects_off": ["ambient"]}) is None
    assert "profile" in check_options({"profile": "shiny"})
    assert "effects_off" in check_options({"effects_off": ["glare"]})


def test_noise_drawn_ahead_is_the_noise_drawn_on_demand_and_waits_for_an_idle_renderer():
    import time

    from scancell.sim.sensor_noise import NoiseBank, frame_noise

    shape = (1024, 1024)  # the smallest frame drawn ahead
    bank = NoiseBank([7, 3], ahead=4)

    def drawn(frame: int, timeout_s: float) -> bool:
        fut = bank._drawn.get((shape, frame))
        t_end = time.monotonic() + timeout_s
        while fut is not None and not fut.done() and time.monotonic() < t_end:
            time.sleep(0.02)
        return fut is not None and fut.done()

    np.testing.assert_array_equal(bank.take(shape, 0), frame_noise(shape, [7, 3, 0]))
    assert drawn(4, 20.0)  # the renderer idle: frames 1 … 4 drawn ahead
    with bank.rendering():
        np.testing.assert_array_equal(bank.take(shape, 1), frame_noise(shape, [7, 3, 1]))
        assert not drawn(5, 0.5)  # never while the renderer works
    assert drawn(5, 20.0)
    for f in (2, 3, 4, 5):
        np.testing.assert_array_equal(bank.take(shape, f), frame_noise(shape, [7, 3, f]))
    small = (100, 120)  # drawn on demand
    np.testing.assert_array_equal(bank.take(small, 9), frame_noise(small, [7, 3, 9]))


def test_a_blur_spanning_a_near_surface_keeps_the_in_focus_pixels_sharp():
    """A camera that sees a surface a few cm from its lens has sigmas of 0.55 to ~40 px: the
    in-focus part must still get its own blur (levels spread evenly blended it with a 14 px
    image), and the large blurs, done on a reduced image, must match the full-size ones."""
    import cv2
    from scancell.sim.cell import _blur, gaussian_blur

    rng = np.random.default_rng(2)
    h, w = 400, 600
    x = np.arange(w, dtype=np.float32)
    image = (100 + 80 * np.cos(2 * np.pi * x / 23.0))[None, :].repeat(h, 0).astype(np.float32)
    image += cv2.GaussianBlur(rng.normal(0, 20, (h, w)).astype(np.float32), (0, 0), 3)
    for s in (8.5, 12.0, 20.0, 41.0):
        got = np.empty_like(image)
        gaussian_blur(image, s, got)
        want = cv2.GaussianBlur(image, (0, 0), s)
        inner = (slice(3 * int(s), h - 3 * int(s)), slice(3 * int(s), w - 3 * int(s)))
        assert np.abs(got - want)[inner].max() < 0.2, s  # DN, against a 160 DN fringe
    sigma = np.full((h, w), 0.6, np.float32)
    sigma[:, 450:] = 40.0  # the near surface, on the right
    out = _blur(image, sigma)
    sharp = cv2.GaussianBlur(image, (0, 0), 0.6)
    np.testing.assert_allclose(out[50:350, 20:300], sharp[50:350, 20:300], atol=0.05)
