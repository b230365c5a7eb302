"""Where tensors are computed: ``--device cpu|cuda|auto`` of ``reconstruct``, ``synth``, ``demo`` and the benchmarks.

What runs on the device and what stays on the CPU (docs/architecture.md, "Devices"):

- **On the device:** the shading (:func:`renderer.shading.shade` runs where its maps are) and the fit's solve —
  every model evaluation, Jacobian, sparse footprint product and PCG iteration of ``auto``'s trial fits and of the
  final one.
- **On the CPU:** ray casting (embree has no GPU path; G-buffers and shadow rays are computed once), building the
  observations from them, the reflectance sharing's k-means (a few thousand points), the metrics and the files.
  The observations move to the device once per fit and the fitted maps come back.

``auto`` is CUDA when torch sees a GPU, else the CPU. Results agree with the CPU's within float32 rounding
(``tests/capture/test_device.py``, marked ``gpu``); CUDA's atomic float additions (``index_add``) make two runs on
the GPU differ in the last bits, which a poorly determined fit can amplify.
"""

from __future__ import annotations

import torch

__all__ = ["DEVICES", "DeviceError", "resolve_device"]

#: the spellings ``--device`` accepts (``cuda:N`` picks a GPU by index as well)
DEVICES = ("auto", "cpu", "cuda")


class DeviceError(ValueError):
    """A device that is not spelled right or that this machine does not have."""


def resolve_device(device: str | torch.device | None = "auto") -> torch.device:
    """The :class:`torch.device` that ``device`` names: ``"auto"`` (or None) is ``cuda`` when torch sees a GPU and
    the CPU otherwise; ``"cpu"``, ``"cuda"`` and ``"cuda:N"`` as torch spells them.

    Raises:
        DeviceError: an unknown name, or CUDA asked for on a machine (or a torch build) without it — the message
            says which, and that ``cpu`` or ``auto`` runs anyway.
    """
    if device is None or (isinstance(device, str) and device == "auto"):
        return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")
    if not isinstance(device, (str, torch.device)):
        raise DeviceError(f"device must be one of {DEVICES} (or 'cuda:N'), got {type(device).__name__} {device!r}")
    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError):
        raise DeviceError(f"unknown device {device!r}: use one of {DEVICES} (or 'cuda:N')") from None
    if dev.type == "cpu":
        return dev
    if dev.type != "cuda":
        raise DeviceError(f"device {device!r} is not supported: use one of {DEVICES} (or 'cuda:N')")
    if not torch.cuda.is_available():
        why = ("this torch is a CPU-only build" if torch.version.cuda is None
               else "torch sees no GPU on this machine")
        raise DeviceError(f"device {device!r} asked for, but {why}: use --device cpu (or auto, which falls back "
                          f"to the CPU), or install a CUDA build of torch on a machine with an NVIDIA GPU")
    if dev.index is not None and dev.index >= torch.cuda.device_count():
        raise DeviceError(f"device {device!r}: this machine has {torch.cuda.device_count()} GPU(s), "
                          f"cuda:0 … cuda:{torch.cuda.device_count() - 1}")
    return dev
