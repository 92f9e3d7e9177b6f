"""Signal processing follows the paper: zero-phase 5 Hz first-order low-pass, increment-end subsampling."""

import numpy as np
import pytest

from twin.processing import increment_ends, loading_phase, lowpass
from twin.protocol import ProtocolSettings, depth_schedule


def test_lowpass_is_zero_phase_and_has_the_butterworth_gain() -> None:
    rate = 100.0
    t = np.arange(0, 20, 1 / rate)
    slow = np.sin(2 * np.pi * 0.2 * t)
    at_cutoff = np.sin(2 * np.pi * 5.0 * t)
    out_slow = lowpass(slow, rate)
    out_cut = lowpass(at_cutoff, rate)
    core = slice(300, -300)
    assert np.max(np.abs(out_slow[core] - slow[core])) < 0.01  # no lag, unit gain far below cutoff
    # forward-backward squares the first-order magnitude: |H|^2 = 1/2 at the cutoff
    gain = np.std(out_cut[core]) / np.std(at_cutoff[core])
    assert gain == pytest.approx(0.5, abs=0.03)


def test_lowpass_rejects_cutoff_above_nyquist() -> None:
    with pytest.raises(ValueError, match="Nyquist"):
        lowpass(np.zeros(100), 8.0)


def test_increment_ends_pick_the_last_sample_of_each_increment() -> None:
    increment = np.array([-1, -1, 0, 0, 0, 1, 1, 2, 3, 3])
    assert increment_ends(increment).tolist() == [4, 6, 7, 9]


def test_loading_phase_switches_after_the_deepest_row() -> None:
    depth = np.array([0.0, 0.1, 0.2, 0.1, 0.0])
    assert loading_phase(depth).tolist() == [0, 0, 0, 1, 1]


def test_depth_schedule_loads_then_unloads_in_steps() -> None:
    settings = ProtocolSettings(step=1e-4, standoff=1e-3, unload=True)
    depths, increments = depth_schedule(3e-4, settings)
    assert np.allclose(depths, [-1e-3, 0, 1e-4, 2e-4, 3e-4, 2e-4, 1e-4, 0, -1e-3])
    assert increments.tolist() == list(range(-1, 8))
    loading_only, _ = depth_schedule(3e-4, ProtocolSettings(unload=False))
    assert loading_only[-1] == pytest.approx(3e-4)


def test_protocol_settings_validation() -> None:
    with pytest.raises(ValueError):
        ProtocolSettings(step=0.0)
    with pytest.raises(ValueError):
        ProtocolSettings(angle_deg=95.0)


def test_a_press_refused_before_its_first_row_has_no_rows_and_no_phases() -> None:
    """The FE may refuse a press at its first step (an indenter on the clamped rim): the campaign then records a
    trajectory without rows, and processing gives none instead of failing on an empty argmax."""
    assert loading_phase(np.zeros(0)).shape == (0,)
    np.testing.assert_array_equal(loading_phase(np.array([0.0, 1.0, 2.0, 1.0])), [0, 0, 0, 1])


def test_a_press_refused_at_once_leaves_the_noise_estimate_finite() -> None:
    """A paper-scale campaign holds presses whose first fe step was refused: one sample, no rows. Its rate is
    undefined; the rows' noise estimate must come from the other presses, as if it were not there."""
    import warnings
    from types import SimpleNamespace

    from twin.analysis.compare import rows_noise_estimate

    rng = np.random.default_rng(3)

    def press(samples: int, rows: int) -> SimpleNamespace:
        time = np.arange(samples) / 100.0
        rate = float(1.0 / np.median(np.diff(time))) if samples > 1 else float("nan")
        force = np.linspace(0, 3, rows)[:, None] + rng.normal(0, 0.01, (rows, 3))
        return SimpleNamespace(raw=SimpleNamespace(time=time), rate_hz=rate, rows={"force": force, "pdc": force[:, 0]})

    presses = [press(500, 40), press(450, 35)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        alone = rows_noise_estimate(presses)
        with_refused = rows_noise_estimate([*presses, press(1, 0)])
        short = lowpass(np.ones((1, 3)), float("nan"))
    assert all(np.isfinite(v) for v in with_refused.values())
    assert with_refused == alone
    assert np.array_equal(short, np.ones((1, 3)))
