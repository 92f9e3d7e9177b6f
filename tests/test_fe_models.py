"""Inflated fe models: the shared builder fills the skin to the manufacturer's thickness; the env cache reuses it."""

from __future__ import annotations

import subprocess
import sys

import pytest

from assets.biotac import make_biotac
from fe.params import SkinParameters
from fe.sensor import SENSOR_THICKNESS
from twin.fe_models import inflated_model, shared_model


def test_the_model_is_inflated_to_the_sensor_s_thickness_and_shared_by_the_envs() -> None:
    model = inflated_model(make_biotac(2e-3), SkinParameters())
    assert model.reference is not None and model.pressure > 0.0
    assert model.thickness(model.reference) == pytest.approx(15.1e-3, abs=1e-6)  # the product manual's figure
    assert SENSOR_THICKNESS == pytest.approx(15.1e-3)
    cached = shared_model(2.0)
    assert cached is shared_model(2.0)
    assert cached.thickness(cached.reference) == pytest.approx(model.thickness(model.reference), abs=1e-9)
    with pytest.raises(ValueError, match="mesh_mm must be in"):
        shared_model(0.1)


def test_the_env_model_path_needs_no_dataset_stack() -> None:
    """env_bench runs on a bare GPU machine: the envs' model builder imports without h5py."""
    blocked = "import sys; sys.modules['h5py'] = None; import twin.envs.fe_batch, twin.fe_models"
    run = subprocess.run([sys.executable, "-c", blocked], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]


def test_the_model_cache_builds_each_model_once_and_drops_the_oldest() -> None:
    from dataclasses import replace

    from twin.fe_models import ModelCache

    dropped = []
    cache = ModelCache(1, on_drop=dropped.append)
    nominal, stiffer = SkinParameters(), replace(SkinParameters(), mu_nh=1.2 * SkinParameters().mu_nh)
    first, result = cache.get(nominal, 2e-3)
    assert result.converged and cache.get(nominal, 2e-3)[0] is first  # built once
    assert cache.get(replace(nominal), 2e-3)[0] is first  # keyed by the values, not the object
    other = cache.get(stiffer, 2e-3)[0]
    assert dropped == [first] and other is not first  # one model held: the oldest went, and was told
    assert other.pressure > first.pressure  # a stiffer skin needs more pressure for the same thickness
    assert cache.get(nominal, 2e-3)[0] is not first and dropped == [first, other]
    with pytest.raises(ValueError, match="at least one model"):
        ModelCache(0)
