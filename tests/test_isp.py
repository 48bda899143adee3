"""ISP (sRGB <-> raw) and raw-domain blur with sensor noise."""
from __future__ import annotations

import colour
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from ev3dgs.errors import InputError
from ev3dgs.sim.blur import add_sensor_noise, blur_frames
from ev3dgs.sim.config import BAYER_PATTERNS, ISPConfig, SensorNoise
from ev3dgs.sim.isp import forward_isp, inverse_isp, linear_to_srgb, srgb_to_linear

CFG = ISPConfig()
GAINS = np.array(CFG.white_balance)
CCM = np.array(CFG.ccm)


def _max_dn(a, b):
    return int(np.abs(a.astype(int) - b.astype(int)).max())


def _reference_raw(linear):
    """Independent inverse ISP (no mosaic): solve CCM @ cam = linear, then undo the white balance."""
    cam = np.linalg.solve(CCM, linear.reshape(-1, 3).T).T
    return (cam / GAINS).reshape(linear.shape)


# ---------------------------------------------------------------- round trips

def test_round_trip_random_images():
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, size=(40, 50, 3), dtype=np.uint8)
    raw = inverse_isp(img, CFG)
    assert raw.shape == img.shape and raw.dtype == np.float64
    assert _max_dn(forward_isp(raw, CFG), img) <= 1


def test_round_trip_all_grey_levels_and_primaries():
    grey = np.repeat(np.arange(256, dtype=np.uint8)[None, :, None], 3, axis=2)
    assert _max_dn(forward_isp(inverse_isp(grey, CFG), CFG), grey) <= 1
    corners = np.array([[[a, b, c] for a in (0, 255) for b in (0, 255) for c in (0, 255)]], dtype=np.uint8)
    assert _max_dn(forward_isp(inverse_isp(corners, CFG), CFG), corners) <= 1


@pytest.mark.parametrize("pattern", BAYER_PATTERNS)
@pytest.mark.parametrize("shape", [(12, 16), (7, 9), (2, 2)])
def test_mosaic_flat_field_round_trip(pattern, shape):
    """A flat colour survives mosaic + OpenCV demosaic: checks the Bayer code mapping for every pattern
    (a wrong code swaps R/B or mixes G into R/B, off by tens of DN for these colours)."""
    cfg = ISPConfig(mosaic=pattern)
    for colour_u8 in [(200, 120, 30), (30, 180, 220), (255, 0, 0), (0, 0, 255), (0, 255, 0), (128, 128, 128)]:
        img = np.broadcast_to(np.array(colour_u8, dtype=np.uint8), shape + (3,)).copy()
        raw = inverse_isp(img, cfg)
        assert raw.shape == shape
        out = forward_isp(raw, cfg)
        assert out.shape == shape + (3,)
        inner = out[1:-1, 1:-1] if min(shape) > 2 else out
        assert _max_dn(inner, img[: inner.shape[0], : inner.shape[1]]) <= 2, (pattern, colour_u8)


@pytest.mark.parametrize("pattern", BAYER_PATTERNS)
def test_mosaic_samples_cfa_channel(pattern):
    img = np.zeros((4, 4, 3))
    img[..., 0], img[..., 1], img[..., 2] = 0.1, 0.2, 0.3
    full = inverse_isp(img, CFG)
    mos = inverse_isp(img, ISPConfig(mosaic=pattern))
    channel = {"R": 0, "G": 1, "B": 2}
    for i in range(2):
        for j in range(2):
            assert mos[i, j] == full[i, j, channel[pattern[2 * i + j]]]


# ---------------------------------------------------------------- colour maths

def test_srgb_wrappers_match_colour_science():
    u8 = np.arange(256, dtype=np.uint8)
    lin = srgb_to_linear(u8)
    np.testing.assert_allclose(lin, colour.cctf_decoding(u8 / 255.0, function="sRGB"), atol=1e-12)
    np.testing.assert_allclose(srgb_to_linear(u8 / 255.0), lin, atol=1e-12)
    np.testing.assert_allclose(linear_to_srgb(lin), u8 / 255.0, atol=1e-9)
    np.testing.assert_allclose(linear_to_srgb(np.array([-1.0, 5.0])), [0.0, 1.0], atol=1e-12)


def test_inverse_isp_linear_float_matches_decoded_srgb():
    rng = np.random.default_rng(2)
    img = rng.integers(0, 256, size=(8, 10, 3), dtype=np.uint8)
    linear = np.asarray(colour.cctf_decoding(img / 255.0, function="sRGB"))
    from_float = inverse_isp(linear, CFG)
    np.testing.assert_allclose(from_float, inverse_isp(img, CFG), atol=1e-12)
    np.testing.assert_allclose(from_float, _reference_raw(linear), atol=1e-12)


def test_white_maps_to_inverse_gains():
    for white in (np.full((3, 3, 3), 255, np.uint8), np.ones((3, 3, 3))):
        np.testing.assert_allclose(inverse_isp(white, CFG), np.broadcast_to(1.0 / GAINS, (3, 3, 3)), atol=1e-12)
    mos = inverse_isp(np.ones((2, 2, 3)), ISPConfig(mosaic="RGGB"))
    np.testing.assert_allclose(mos, [[1 / GAINS[0], 1 / GAINS[1]], [1 / GAINS[1], 1 / GAINS[2]]], atol=1e-12)


# ---------------------------------------------------------------- blur

@pytest.mark.parametrize("mosaic", ["none", "GRBG"])
def test_blur_identical_frames_returns_frame(mosaic):
    cfg = ISPConfig(mosaic=mosaic)
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, size=(9, 11, 3), dtype=np.uint8)
    out = blur_frames(np.stack([img] * 4), cfg)
    assert out.dtype == np.uint8 and out.shape == img.shape
    np.testing.assert_array_equal(out, forward_isp(inverse_isp(img, cfg), cfg))
    if mosaic == "none":
        assert _max_dn(out, img) <= 1


def test_blur_two_linear_frames_is_mean_raw():
    rng = np.random.default_rng(4)
    a, b = rng.uniform(0, 1, size=(2, 6, 7, 3))
    expected = forward_isp((_reference_raw(a) + _reference_raw(b)) / 2, CFG)
    np.testing.assert_array_equal(blur_frames(np.stack([a, b]), CFG), expected)
    # averaging in raw (linear light), not in sRGB: black + white is not mid-grey 128
    bw = np.stack([np.zeros((1, 1, 3), np.uint8), np.full((1, 1, 3), 255, np.uint8)])
    assert blur_frames(bw, CFG)[0, 0, 0] == round(255 * float(colour.cctf_encoding(0.5, function="sRGB")))


# ---------------------------------------------------------------- sensor noise

@pytest.mark.parametrize("iso", [100, 1600])
def test_noise_variance_matches_shot_plus_read(iso):
    noise = SensorNoise(iso=iso, full_well_electrons=10000, read_noise_electrons=3)
    fw = 10000 * 100 / iso
    raw = np.full((400, 500), 0.3)
    noisy = add_sensor_noise(raw, noise, np.random.default_rng(5))
    expected_var = (0.3 * fw + 3.0 ** 2) / fw ** 2
    assert noisy.var() == pytest.approx(expected_var, rel=0.03)
    assert noisy.mean() == pytest.approx(0.3, abs=3 * np.sqrt(expected_var / raw.size))


def test_higher_iso_is_noisier_and_seeded():
    field = np.full((2, 64, 64, 3), 0.18)
    low = blur_frames(field, CFG, SensorNoise(iso=100), seed=1).astype(float)
    high = blur_frames(field, CFG, SensorNoise(iso=3200), seed=1).astype(float)
    assert high.std() > 2 * low.std()
    again = blur_frames(field, CFG, SensorNoise(iso=3200), seed=1)
    np.testing.assert_array_equal(again, high.astype(np.uint8))
    assert not np.array_equal(blur_frames(field, CFG, SensorNoise(iso=3200), seed=2), again)


@pytest.mark.parametrize("mosaic", ["none", "BGGR"])
def test_extremes_stay_finite_and_clip(mosaic):
    cfg = ISPConfig(mosaic=mosaic)
    assert np.all(blur_frames(np.zeros((2, 6, 6, 3)), cfg) == 0)
    assert np.all(blur_frames(np.zeros((2, 6, 6, 3), np.uint8), cfg) == 0)
    for bright in (np.full((2, 6, 6, 3), 255, np.uint8), np.full((2, 6, 6, 3), 1.0), np.full((2, 6, 6, 3), 1e3)):
        assert np.all(blur_frames(bright, cfg) == 255)
    hdr_raw = inverse_isp(np.full((4, 4, 3), 1e3), cfg)
    assert np.all(np.isfinite(hdr_raw)) and np.all(forward_isp(hdr_raw, cfg) == 255)
    # blown highlights go white, not magenta: a saturated green-ish HDR pixel still clips to 255 everywhere
    hdr = np.broadcast_to(np.array([2e2, 1e3, 5e2]), (2, 6, 6, 3))
    assert np.all(blur_frames(hdr, cfg) == 255)


@pytest.mark.parametrize("mosaic", ["none", "BGGR"])
def test_extremes_with_noise(mosaic):
    cfg, noise = ISPConfig(mosaic=mosaic), SensorNoise(iso=800)
    dark = blur_frames(np.zeros((2, 16, 16, 3)), cfg, noise)
    assert 0 < dark.max() < 60  # read noise only
    for scale in (1e3, 1e30):  # saturated well (+ read noise): stays finite, within a few DN of white
        out = blur_frames(np.full((2, 16, 16, 3), scale), cfg, noise)
        assert out.min() >= 245


# ---------------------------------------------------------------- bad inputs

@pytest.mark.parametrize("frames", [
    np.zeros((4, 4, 3)),                      # no S axis
    np.zeros((2, 4, 4, 4)),                   # 4 channels
    np.zeros((0, 4, 4, 3)),                   # no frames
    np.zeros((2, 4, 0, 3)),                   # empty image
    np.full((1, 2, 2, 3), np.nan),
    np.full((1, 2, 2, 3), np.inf),
    -np.ones((1, 2, 2, 3)),
    np.zeros((1, 2, 2, 3), dtype=np.int32),   # neither uint8 nor float
])
def test_bad_frames_raise(frames):
    with pytest.raises(InputError):
        blur_frames(frames)


def test_bad_isp_inputs_raise():
    with pytest.raises(InputError):
        inverse_isp(np.zeros((4, 4)), CFG)
    with pytest.raises(InputError):
        inverse_isp(np.zeros((1, 4, 3)), ISPConfig(mosaic="RGGB"))  # too small to demosaic
    with pytest.raises(InputError):
        forward_isp(np.zeros((4, 4)), CFG)  # mosaic raw without a mosaic config
    with pytest.raises(InputError):
        forward_isp(np.zeros((4, 4, 3)), ISPConfig(mosaic="RGGB"))
    with pytest.raises(InputError):
        forward_isp(np.full((4, 4, 3), np.nan), CFG)


# ---------------------------------------------------------------- property

@settings(max_examples=50, deadline=None)
@given(arrays(np.uint8, st.tuples(st.integers(1, 6), st.integers(1, 6), st.just(3))))
def test_round_trip_property(img):
    assert _max_dn(forward_isp(inverse_isp(img, CFG), CFG), img) <= 1
