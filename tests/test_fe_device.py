"""The per-trajectory FE path stays on warp's CPU device whatever warp's default device is.

On a CUDA machine warp's default device is `cuda:0`; a `ShellSystem` array or launch that took the default
would land on the GPU, where the system's writes through `.numpy()` views are lost. Here the default
device is replaced by a sentinel that fails on any use, every launch must name the CPU device, and every
warp array the system holds must live on it, through a 2 mm BioTac inflation and three frictional,
viscoelastic indentation steps (every kernel of the path launched).
"""

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import warp as wp

from assets.biotac import make_biotac
from fe import bending, contact, membrane, viscoelastic, volume
from fe.params import SkinParameters
from fe.sensor import BioTacModel
from fe.shell import CPU_DEVICE, ShellSystem


class _DefaultDeviceUsed:
    """Stands in for warp's default device: any use of it fails the test."""

    def __getattr__(self, name: str) -> None:
        raise AssertionError(f"warp's default device was used (.{name}); pass device=CPU_DEVICE")


def _warp_arrays(system: ShellSystem) -> dict[str, wp.array]:
    """Every warp array the system holds, by attribute (buffers as `_buf[name]`)."""
    held = {name: value for name, value in vars(system).items() if isinstance(value, wp.array)}
    held.update({f"_buf[{name}]": value for name, value in system._buf.items()})
    return held


def test_shell_system_allocates_and_launches_only_on_the_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    launched: set[str] = set()
    launch: Callable[..., Any] = wp.launch

    def cpu_launch(kernel: Any, *args: Any, **kwargs: Any) -> Any:
        """`wp.launch` that insists on an explicit CPU device."""
        assert kwargs.get("device") == CPU_DEVICE, f"{kernel.key} launched without device={CPU_DEVICE!r}"
        launched.add(kernel.key)
        return launch(kernel, *args, **kwargs)

    runtime = wp.get_device(CPU_DEVICE).runtime
    monkeypatch.setattr(runtime, "default_device", _DefaultDeviceUsed())
    monkeypatch.setattr(wp, "launch", cpu_launch)

    model = BioTacModel(make_biotac(max_edge=2e-3), SkinParameters(friction=0.5, relaxation_fraction=0.3))
    assert model.inflate().converged
    increments = list(
        model.indent("sphere_medium", np.array([-6e-3, 0.0, -9e-3]), depth=0.3e-3, step=0.1e-3, speed=1e-3)
    )

    assert len(increments) == 4 and all(inc.converged for inc in increments)
    assert increments[-1].force[2] > 0.0
    kernels = [membrane.membrane_kernel, viscoelastic.frozen_stress_kernel, bending.bending_kernel]
    kernels += [volume.volume_kernel, contact.core_contact_kernel, contact.indenter_contact_kernel]
    kernels += [contact.indenter_gap_kernel]
    assert launched == {kernel.key for kernel in kernels}
    system = model.system
    assert system._frozen_stress is not None
    off_cpu = {name: str(a.device) for name, a in _warp_arrays(system).items() if not a.device.is_cpu}
    assert not off_cpu
    assert system._core_mesh.device.is_cpu
