"""DeepNet prepared for labelling on one device: the fast path that gives the same labels.

- **Layout.** Channels-last weights (``channels_last_3d``): the layout oneDNN's CPU
  convolutions and the GPU's tensor cores want (1.5x on a CPU, ``docs/baseline_cnn.md``).
- **Precision** (``[prediction] precision``). ``"auto"``: float16 weights and activations
  on a CUDA GPU (occupancy cubes, 0 or 1, are exact in it; half the bytes of float32 and
  the tensor cores' rate), float32 on a CPU, where bfloat16 autocast was measured no
  faster than float32 (AVX2 cores, and AVX-512/AMX ones) and changes labels (0.4 % of the
  points of an untrained network). A tile whose float16 logits are not all finite is
  labelled again in float32, so an overflow never decides a label. ``"float32"``: the
  reference arithmetic everywhere.
- **Fusion** (``[prediction] compile``). ``torch.compile`` fuses each path's ReLU and
  pooling into the convolutions' epilogues and the element-wise casts away (3.3x on an
  H100 for the eager float16 network; 1.2-1.5x per CPU second on 2 CPU cores, same logits).
  Compiling costs tens of seconds (~50 s on a busy 2-core CPU, ~8 s with a warm cache), so
  ``"auto"`` compiles once the points this process labels (counted over scans, plus the
  scan about to be labelled, :meth:`InferenceNetwork.expect`) pass
  :data:`COMPILE_AFTER_POINTS` for the device. It is compiled once per process and model,
  for one batch shape (smaller batches are padded to it), never per scan or tile. Where
  compilation is not available or fails, a warning is logged and the eager network runs.

Labels on a CPU equal the reference path's (eager float32 network in the default layout)
except where two classes' logits tie to float32 rounding (tested); on a GPU float16 labels
may differ from float32 ones where the two best logits are within float16 rounding.

Needs the ``[torch]`` extra.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from semantic3d.core.errors import require

torch: Any = require("torch", "torch")

__all__ = ["COMPILE_AFTER_POINTS", "InferenceNetwork"]

logger = logging.getLogger(__name__)

COMPILE_AFTER_POINTS = {"cpu": 100_000, "cuda": 5_000_000}
"""Points labelled by one process after which ``compile = "auto"`` compiles the network:
where the time saved passes a cold compilation's (CPU: ~250 points/s eager, 1.46x
compiled, ~50 s to compile; GPU: ~200 k points/s eager float16, ~2x compiled)."""

Compiler = Callable[[Any], Any]


class InferenceNetwork:
    """A network's labelling form on one device.

    Args:
        network: the trained :class:`~semantic3d.baselines.cnn.network.DeepNet` (its
            weights are shared, not copied, where the arithmetic is float32).
        device: where it runs.
        precision: ``"auto"`` or ``"float32"`` (see the module docstring).
        compile: ``"auto"``, ``"always"`` or ``"never"``.
        batch_size: the batch shape it is compiled for.
        logit_mask: ``(n_classes,)`` added to the logits (``-inf`` for classes not
            trained on).
        compiler: what compiles a module (``torch.compile``; replaceable for tests).
    """

    def __init__(
        self,
        network: Any,
        *,
        device: Any,
        precision: str,
        compile: str,
        batch_size: int,
        logit_mask: Any,
        compiler: Compiler | None = None,
    ) -> None:
        self.device = torch.device(device)
        self.batch_size = batch_size
        self.compile_mode = compile
        self.reference = network.eval().to(self.device, memory_format=torch.channels_last_3d)
        half = precision == "auto" and self.device.type == "cuda"
        self.dtype = torch.float16 if half else torch.float32
        if half:
            import copy

            self.fast = copy.deepcopy(self.reference).to(dtype=torch.float16)
        else:
            self.fast = self.reference
        self.logit_mask = logit_mask.to(self.device)
        self._compiler = compiler if compiler is not None else _torch_compile
        self._compiled: Any = None
        self._compile_failed = False
        self._lock = threading.Lock()
        self.points_seen = 0
        self._expected = 0

    @property
    def compiled(self) -> bool:
        """Whether the compiled network runs."""
        return self._compiled is not None

    def expect(self, n_points: int) -> None:
        """Say how many points are about to be labelled (a scan's): ``compile = "auto"``
        decides with it."""
        self._expected = max(int(n_points), 0)

    def classify(self, cubes: Any, *, precise: bool = False) -> tuple[Any, Any]:
        """Class indices ``(n,)`` and whether every logit was finite (a 0-d bool tensor),
        on the device, of ``(n, n_scales, C, C, C)`` cubes; nothing waits for the device.

        ``precise`` runs the float32 reference network (eagerly).
        """
        n = cubes.shape[0]
        with torch.inference_mode():
            if precise:
                logits = self.reference(cubes.to(torch.float32))
            else:
                logits = self._forward(cubes.to(self.dtype))
            logits = logits[:n].float()
            finite = torch.isfinite(logits).all()
            index = torch.argmax(logits + self.logit_mask, dim=1)
        self.points_seen += n
        return index, finite

    def _forward(self, cubes: Any) -> Any:
        if self._compiled is None and self._should_compile():
            with self._lock:  # Dask workers may label tiles of one model in threads
                if self._compiled is None and not self._compile_failed:
                    self._compile()
        if self._compiled is None:
            return self.fast(cubes)
        n = cubes.shape[0]
        if n < self.batch_size:  # one shape for the compiled graph
            padding = cubes.new_zeros((self.batch_size - n, *cubes.shape[1:]))
            cubes = torch.cat([cubes, padding])
        try:
            return self._compiled(cubes)
        except Exception as exc:  # the first call compiles: any backend error lands here
            logger.warning("torch.compile of the network failed, running it eagerly: %s", exc)
            self._compiled = None
            self._compile_failed = True
            return self.fast(cubes)

    def _should_compile(self) -> bool:
        if self._compile_failed or self.compile_mode == "never":
            return False
        if self.compile_mode == "always":
            return True
        kind = "cuda" if self.device.type == "cuda" else "cpu"
        return self.points_seen + self._expected >= COMPILE_AFTER_POINTS[kind]

    def _compile(self) -> None:
        try:
            self._compiled = self._compiler(self.fast)
        except Exception as exc:  # no dynamo on this Python / platform
            logger.warning("torch.compile is not available, running the network eagerly: %s", exc)
            self._compile_failed = True


def _torch_compile(module: Any) -> Any:
    return torch.compile(module, dynamic=False)
