"""The FE engine asked for warp's CPU device stays on it whatever warp's default device is.

On a CUDA machine warp's default device is `cuda:0`; an engine array or launch that took the default would
land on the GPU, apart from the rest of the solve. Here the default device is replaced by a sentinel that
fails on any use, every launch must name a CPU device, and every warp array (and the core's BVH) held by the
engine (`fe.batched_stepper.BatchedStepper`: its `BatchedShell`, block matrix, linear solver, viscoelastic
state) must live on it, through a 2 mm BioTac inflation and three frictional, viscoelastic indentation steps
(every energy kernel of the path launched). On the CPU the engine's linear algebra is the sparse direct one.
"""

from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import warp as wp

from assets.biotac import make_biotac
from assets.indenters import get_indenter
from fe import bending, contact, membrane, volume
from fe.indentation import IndentationStepper, drive
from fe.linsolve import BatchedDirectSolver
from fe.params import SkinParameters
from fe.sensor import BioTacModel

CPU_DEVICE = "cpu"


class _DefaultDeviceUsed:
    """Stands in for warp's default device: any use of it fails the test."""

    def __getattr__(self, name: str) -> None:
        raise AssertionError(f"warp's default device was used (.{name}); pass device={CPU_DEVICE!r}")


def _warp_objects(root: object) -> Iterator[tuple[str, wp.array | wp.Mesh]]:
    """Every warp array and mesh reachable from `root` through attributes of fe objects, dicts, lists and
    tuples, by access path."""
    seen: set[int] = set()
    stack: list[tuple[str, object]] = [("engine", root)]
    while stack:
        path, obj = stack.pop()
        if id(obj) in seen:
            continue
        seen.add(id(obj))
        if isinstance(obj, wp.array | wp.Mesh):
            yield path, obj
        elif isinstance(obj, dict):
            stack.extend((f"{path}[{k!r}]", v) for k, v in obj.items())
        elif isinstance(obj, list | tuple):
            stack.extend((f"{path}[{i}]", v) for i, v in enumerate(obj))
        elif type(obj).__module__.startswith("fe.") and hasattr(obj, "__dict__"):
            stack.extend((f"{path}.{k}", v) for k, v in vars(obj).items())


def test_engine_allocates_and_launches_only_on_the_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    launched: set[str] = set()
    launch: Callable[..., Any] = wp.launch

    def cpu_launch(kernel: Any, *args: Any, **kwargs: Any) -> Any:
        """`wp.launch` that insists on an explicit CPU device."""
        device = kwargs.get("device")
        assert device is not None, f"{kernel.key} launched without a device"
        assert wp.get_device(device).is_cpu, f"{kernel.key} launched on {device}"
        launched.add(kernel.key)
        return launch(kernel, *args, **kwargs)

    runtime = wp.get_device(CPU_DEVICE).runtime
    monkeypatch.setattr(runtime, "default_device", _DefaultDeviceUsed())
    monkeypatch.setattr(wp, "launch", cpu_launch)

    model = BioTacModel(make_biotac(max_edge=2e-3), SkinParameters(friction=0.5, relaxation_fraction=0.3))
    assert model.inflate().converged
    # BioTacModel.indent(..., device=CPU_DEVICE), with its stepper kept for inspection.
    trajectory = model.plan_trajectory(
        get_indenter("sphere_medium"), np.array([-6e-3, 0.0, -9e-3]), 0.0, 0.0, 0.3e-3, 1e-4
    )
    trajectory = replace(trajectory, times=trajectory.depths / 1e-3)
    stepper = IndentationStepper(model.inflated_skin(), "sphere_medium", trajectory.touch_point, CPU_DEVICE)
    increments = list(drive(stepper, trajectory))

    assert len(increments) == 4 and all(inc.converged for inc in increments)
    assert increments[-1].force[2] > 0.0
    kernels = [membrane.membrane_kernel, bending.bending_kernel]
    kernels += [volume.volume_kernel, contact.core_contact_kernel, contact.indenter_friction_kernel]
    kernels += [contact.indenter_surface_kernel, contact.indenter_gap_kernel, contact.indenter_face_gap_kernel]
    kernels += [contact.indenter_skin_clearance_kernel]
    assert {kernel.key for kernel in kernels} <= launched
    engine = stepper.engine
    assert engine.relaxation is not None and engine.shell.relaxes
    assert isinstance(engine.shell.linear, BatchedDirectSolver)
    assert engine.shell._core_mesh is not None
    for root in (engine, model._inflation):
        held = dict(_warp_objects(root))
        assert any(".shell.buf[" in name for name in held) and any("_core_mesh" in name for name in held)
        off_cpu = {name: str(a.device) for name, a in held.items() if not wp.get_device(a.device).is_cpu}
        assert not off_cpu
