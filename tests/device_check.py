"""A stand-in accelerator, so that CPU-only CI catches what would fail on a GPU.

Inside `stand_in_device()`, tensors moved to STAND_IN ("meta" by name) keep their data in CPU
memory but report that device, and every operation that mixes them with CPU tensors fails as
it does on CUDA ("Expected all tensors to be on the same device"), except where CUDA allows it:
0-dim CPU tensors as scalars, and copies between devices (.to, .cpu, copy_). `.numpy()` of a
stand-in tensor fails as it does for a CUDA tensor. Random numbers for the device need a
generator made for it (torch.Generator(device=STAND_IN)); a CPU generator fails, as on CUDA.

The computation itself is the CPU's, so a result on the stand-in device must equal the CPU's
bit for bit: that is the oracle of tests/test_devices.py. `Transfers` counts the copies
between host and device, to check what a step moves.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten, tree_map

STAND_IN = torch.device("meta")
CPU = torch.device("cpu")


class DeviceMixing(RuntimeError):
    """What CUDA raises when an operation mixes devices."""


@dataclass
class Transfers:
    """Copies between host and stand-in device of tensors with more than one element (scalars
    read with .item() or bool() are synchronisations, not data movement)."""

    to_host: list[tuple[int, ...]] = field(default_factory=list)
    to_device: list[tuple[int, ...]] = field(default_factory=list)

    def note(self, tensor: torch.Tensor, to_device: bool) -> None:
        if tensor.numel() > 1:
            (self.to_device if to_device else self.to_host).append(tuple(tensor.shape))


_transfers: Transfers | None = None


class OnDevice(torch.Tensor):
    """A CPU tensor `elem` that says it is on STAND_IN."""

    elem: torch.Tensor
    __torch_function__ = torch._C._disabled_torch_function_impl

    @staticmethod
    def __new__(cls, elem: torch.Tensor) -> OnDevice:
        assert type(elem) is torch.Tensor and elem.device == CPU, (type(elem), elem.device)
        wrapper = torch.Tensor._make_wrapper_subclass(
            cls,
            elem.size(),
            strides=elem.stride(),
            storage_offset=elem.storage_offset(),
            dtype=elem.dtype,
            device=STAND_IN,
            requires_grad=elem.requires_grad,
        )
        wrapper.elem = elem
        return wrapper

    def __repr__(self) -> str:  # type: ignore[override]
        return f"OnDevice({self.elem!r})"

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):  # type: ignore[override]
        kwargs = dict(kwargs or {})
        flat, _ = tree_flatten((args, kwargs))
        host = [t for t in flat if isinstance(t, torch.Tensor) and not isinstance(t, OnDevice)]
        for t in host:
            if t.device.type == STAND_IN.type:
                raise RuntimeError(
                    f"{func}: torch made a tensor on {STAND_IN} without data; the stand-in "
                    "device needs a rule for this call (tests/device_check.py)"
                )
        if func is torch.ops.aten.copy_.default:  # copies may cross devices, as on CUDA
            destination, source = args[0], args[1]
            if _transfers is not None and isinstance(source, OnDevice) != isinstance(
                destination, OnDevice
            ):
                _transfers.note(source, to_device=isinstance(destination, OnDevice))
            _unwrap(destination).copy_(_unwrap(source), *args[2:], **kwargs)
            return destination
        mixed = [tuple(t.shape) for t in host if t.dim() > 0]
        if mixed:
            raise DeviceMixing(
                f"Expected all tensors to be on the same device, but {func} got tensors on "
                f"{STAND_IN} and CPU tensors of shapes {mixed}"
            )
        if "device" in kwargs:
            kwargs["device"] = CPU
        out = func(*tree_map(_unwrap, args), **tree_map(_unwrap, kwargs))
        return tree_map(_wrap, out)


def _unwrap(x: Any) -> Any:
    return x.elem if isinstance(x, OnDevice) else x


def _wrap(x: Any) -> Any:
    return OnDevice(x) if type(x) is torch.Tensor else x


def _on_stand_in(device: Any) -> bool:
    return device is not None and torch.device(device).type == STAND_IN.type


class _StandInGenerator(torch.Generator):
    """torch.Generator(device=STAND_IN): a CPU generator that is marked as the device's."""

    def __new__(cls, device: Any = "cpu") -> torch.Generator:
        if _on_stand_in(device):
            return super().__new__(cls, "cpu")
        return torch._C.Generator(device)


class _Mode(TorchFunctionMode):
    """Moves to and from the stand-in device, and factories that name it."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        generator = kwargs.get("generator")
        if generator is not None:
            ours = isinstance(generator, _StandInGenerator)
            if ours != _on_stand_in(kwargs.get("device", _device_of(args))):
                raise DeviceMixing(f"{func.__name__}: a generator of another device")
        if func is torch.Tensor.to:
            device, dtype, _, _ = torch._C._nn._parse_to(*args[1:], **kwargs)
            return _moved(args[0], device, dtype)
        if func is torch.Tensor.cpu:
            return _moved(args[0], CPU, None)
        if func in (torch.Tensor.numpy, torch.Tensor.__array__) and isinstance(args[0], OnDevice):
            raise TypeError(
                f"can't convert {STAND_IN} device type tensor to numpy. Use Tensor.cpu() to "
                "copy the tensor to host memory first."
            )
        if func is torch.Tensor.tolist and isinstance(args[0], OnDevice):  # a read, as on CUDA
            return args[0].elem.tolist()
        if func is torch.Tensor.new_tensor and isinstance(args[0], OnDevice):
            return OnDevice(args[0].elem.new_tensor(*args[1:], **kwargs))
        if func is torch.where and isinstance(_device_of(args), torch.device):
            # CUDA turns a Python scalar into a tensor on the other operand's device; on the
            # stand-in that would be a tensor without data, so make it a CPU scalar tensor.
            like = next(a for a in args if isinstance(a, torch.Tensor) and a.dtype != torch.bool)
            args = tuple(
                torch.tensor(a, dtype=like.dtype) if isinstance(a, (int, float)) else a
                for a in args
            )
        if _on_stand_in(kwargs.get("device")):
            kwargs["device"] = CPU
            with torch._C.DisableTorchFunction():
                out = func(*args, **kwargs)
            return tree_map(_wrap, out)
        return func(*args, **kwargs)


class _Factories(TorchDispatchMode):
    """Tensors that torch's own C++ makes on the stand-in device (zeros in a backward
    formula, a scalar turned into a tensor) get CPU memory too, instead of none."""

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        flat, _ = tree_flatten(args)
        if _on_stand_in(kwargs.get("device")) and not any(
            isinstance(t, torch.Tensor) for t in flat
        ):
            kwargs["device"] = CPU
            return tree_map(_wrap, func(*args, **kwargs))
        return func(*args, **kwargs)


def _device_of(args: Any) -> torch.device | None:
    """STAND_IN when any tensor argument is on it."""
    flat, _ = tree_flatten(args)
    return STAND_IN if any(isinstance(t, OnDevice) for t in flat) else None


def _moved(tensor: torch.Tensor, device: torch.device | None, dtype: torch.dtype | None) -> Any:
    """tensor.to(device, dtype) across the stand-in boundary."""
    dtype = dtype or tensor.dtype
    on_device = isinstance(tensor, OnDevice)
    if device is None or _on_stand_in(device) == on_device:  # no change of device
        if dtype == tensor.dtype:
            return tensor
        with torch._C.DisableTorchFunction():
            return tensor.to(dtype)
    if device.type not in (CPU.type, STAND_IN.type):
        raise RuntimeError(f"the stand-in device test cannot move tensors to {device}")
    if tensor.grad_fn is not None:
        raise RuntimeError("the stand-in device cannot move a tensor with autograd history")
    source = tensor.elem if on_device else tensor.detach()
    if _transfers is not None:
        _transfers.note(source, to_device=not on_device)
    copy = source.to(dtype=dtype, copy=True)
    if on_device:
        return copy.requires_grad_(tensor.requires_grad) if tensor.requires_grad else copy
    moved = OnDevice(copy)
    # A move keeps the autograd history, as .to() does; a leaf stays a leaf.
    return moved.requires_grad_(tensor.requires_grad) if tensor.requires_grad else moved


@contextlib.contextmanager
def stand_in_device(monkeypatch: Any) -> Iterator[Transfers]:
    """Run the block with STAND_IN usable as a device; yields the transfer counts."""
    global _transfers
    monkeypatch.setattr(torch, "Generator", _StandInGenerator)
    # Views of wrapper tensors cannot be made in inference mode (torch cannot give them a
    # version counter); no_grad is the same computation without that.
    monkeypatch.setattr(torch, "inference_mode", lambda mode=True: torch.no_grad())
    _transfers = Transfers()
    try:
        with _Mode(), _Factories():
            yield _transfers
    finally:
        _transfers = None
