"""Dark, flat and saturated images named from their grey levels (pure, no camera)."""

from __future__ import annotations

import numpy as np
import pytest

from config.machine import load_machine
from controller.frames.camera.image_check import (
    DARK_LEVEL,
    FLAT_SPAN,
    SATURATED_FRACTION,
    ImageProblem,
    image_problems,
)
from controller.frames.camera.source import settings_from_config
from core.errors import ConfigError

RNG = np.random.default_rng(0)
H, W = 120, 160


def _ramp(scale: float) -> np.ndarray:
    """Aravis' fake camera's test image: a diagonal ramp times (1 + gain + log10(exp / 10 ms))."""
    y, x = np.mgrid[0:H, 0:W]
    return np.clip(((x + y) % 255) * scale, 0, 255).astype(np.uint8)


def _wood(mean: float, sd: float) -> np.ndarray:
    return np.clip(RNG.normal(mean, sd, (H, W)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize(("image", "expected"), [
    (np.zeros((H, W), np.uint8), (ImageProblem.DARK,)),  # the fake at 0.1 ms: black
    (_ramp(0.05), (ImageProblem.DARK,)),  # at most 12: still too dark to measure
    (_ramp(1.0), ()),  # the fake at 10 ms, 0 dB
    (_wood(110.0, 25.0), ()),  # a lit board
    (_wood(40.0, 6.0), ()),  # a dim board with texture
    (np.full((H, W), 128, np.uint8), (ImageProblem.FLAT,)),  # one grey
    (_wood(128.0, 1.0), (ImageProblem.FLAT,)),  # noise only: +-3 levels
    (np.full((H, W), 255, np.uint8), (ImageProblem.SATURATED,)),
    (_ramp(4.0), (ImageProblem.SATURATED,)),  # the fake at +3 dB: 3/4 clipped
])
def test_image_problems(image, expected):
    problems, levels = image_problems(image)
    assert problems == expected, levels.describe()


def test_the_thresholds_at_their_edges():
    img = np.full((100, 100), DARK_LEVEL - 1, np.uint8)
    img[:, :50] = 0  # 99th percentile DARK_LEVEL - 1: dark
    assert image_problems(img)[0] == (ImageProblem.DARK,)
    img[:2, :] = DARK_LEVEL  # 2 % at DARK_LEVEL: no longer dark (spans 0..16: not flat)
    assert image_problems(img)[0] == ()
    img = np.full((100, 100), 100, np.uint8)
    img[:, :50] = 100 + FLAT_SPAN - 1
    assert image_problems(img)[0] == (ImageProblem.FLAT,)
    img[:, :50] = 100 + FLAT_SPAN
    assert image_problems(img)[0] == ()
    img = _ramp(1.0)
    n = int(SATURATED_FRACTION * img.size)
    img.ravel()[:n] = 255  # the ramp itself has no pixel at 255: exactly the fraction
    assert image_problems(img)[0] == ()
    img.ravel()[n] = 255
    assert image_problems(img)[0] == (ImageProblem.SATURATED,)


def test_levels_describe_the_image_and_bad_input_is_refused():
    _, lv = image_problems(np.zeros((4, 4), np.uint8))
    assert lv.describe() == ("grey levels 0..0 (1st..99th percentile), mean 0.0, 0.0 % at 255")
    with pytest.raises(ValueError, match="Mono8"):
        image_problems(np.zeros((4, 4), np.uint16))
    with pytest.raises(ValueError, match="at least one pixel"):
        image_problems(np.zeros((0, 4), np.uint8))


class _RigCamera:
    width, height, exposure_ms = 659, 493, 0.1


def test_the_fake_cameras_get_their_own_exposure_unless_one_is_set(tmp_path):
    shipped = load_machine(None).frames
    assert shipped.exposure_us == 0.0 and shipped.fake_exposure_us == 10_000.0
    fake = settings_from_config(shipped, rig_camera=_RigCamera(), camera_id="Fake_1")
    real = settings_from_config(shipped, rig_camera=_RigCamera(), camera_id="192.168.10.20")
    assert fake.exposure_us == 10_000.0 and real.exposure_us == pytest.approx(100.0)

    def frames(table: str):
        p = tmp_path / "m.toml"
        p.write_text(f"[frames]\n{table}\n")
        return load_machine(p).frames  # over the shipped file

    own = frames("exposure_us = 2500.0")
    assert settings_from_config(own, rig_camera=_RigCamera(), camera_id="Fake_1").exposure_us \
        == 2500.0
    off = frames("fake_exposure_us = 0.0")
    assert settings_from_config(off, rig_camera=_RigCamera(), camera_id="Fake_1").exposure_us \
        == pytest.approx(100.0)
    with pytest.raises(ConfigError, match="frames.fake_exposure_us"):
        frames("fake_exposure_us = -1.0")
