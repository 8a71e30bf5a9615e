"""Issue 33: FSRCNN's torch back end with ``upscale.device`` (cpu | cuda | auto) and ``upscale.tf32``."""

from __future__ import annotations

import numpy as np
import pytest

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.types import Image2D
from nirspi_pipe.upscale.fsrcnn import FSRCNN

# marker torch: deselected by default (no skip in a run without torch); `pytest -m torch` after
# `pip install '.[train]'`. torch is imported inside the tests, so collecting them needs no torch.
pytestmark = pytest.mark.torch


def _image() -> Image2D:
    yy, xx = np.mgrid[0:12, 0:10] / 10.0
    return Image2D(np.clip(0.5 + 0.3 * np.sin(5 * xx + 2 * yy), 0, 1))


def test_torch_backend_agrees_with_numpy_and_records_its_device() -> None:
    ref = FSRCNN(scale=3).upscale(_image())
    out = FSRCNN(scale=3, backend="torch", device="cpu").upscale(_image())
    assert np.max(np.abs(out.data - ref.data)) <= 1e-5
    assert (out.info["backend"], out.info["device"], out.info["tf32"]) == ("torch", "cpu", False)
    assert ref.info["backend"] == "numpy"


def test_auto_falls_back_to_the_cpu_and_cuda_fails_in_one_line() -> None:
    import torch

    want = "cuda" if torch.cuda.is_available() else "cpu"
    assert FSRCNN(scale=2, backend="torch", device="auto").upscale(_image()).info["device"] == want
    if not torch.cuda.is_available():
        with pytest.raises(NirspiError, match=r"^upscale.device=cuda: torch .* sees no CUDA GPU here; use"):
            FSRCNN(scale=2, backend="torch", device="cuda")


@pytest.mark.parametrize(("key", "value"), [("backend", "cuda"), ("device", "gpu"), ("tf32", "yes")])
def test_bad_keys_fail_in_one_line(key: str, value: str) -> None:
    with pytest.raises(ConfigError, match=f"^{key}="):
        FSRCNN(scale=2, **{key: value})  # type: ignore[arg-type]


def test_tf32_switches_are_restored_after_the_call() -> None:
    import torch

    from nirspi_pipe.upscale.fsrcnn import fsrcnn_forward_torch, load_weights

    b = torch.backends
    before = (b.cuda.matmul.allow_tf32, b.cudnn.allow_tf32)
    try:
        b.cuda.matmul.allow_tf32, b.cudnn.allow_tf32 = True, True
        fsrcnn_forward_torch(_image().data, load_weights(2), "cpu", tf32=False)
        assert (b.cuda.matmul.allow_tf32, b.cudnn.allow_tf32) == (True, True)
        b.cuda.matmul.allow_tf32, b.cudnn.allow_tf32 = False, False
        fsrcnn_forward_torch(_image().data, load_weights(2), "cpu", tf32=True)
        assert (b.cuda.matmul.allow_tf32, b.cudnn.allow_tf32) == (False, False)
    finally:
        b.cuda.matmul.allow_tf32, b.cudnn.allow_tf32 = before
