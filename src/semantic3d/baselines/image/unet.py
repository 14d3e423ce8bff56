"""The modern variant: a small U-Net encoder-decoder on the same cube faces (``[torch]``).

Not in the paper, whose image baseline is the hierarchical fields method; the paper names
encoder-decoder networks such as SegNet as the modern approach to image segmentation
(Section 3), and this is the same family (an encoder of convolutions and down-sampling, a decoder of up-sampling, here with
U-Net's skip connections) at a size a CPU trains in minutes. Input channels: colour
(0..1), whether the pixel shows a point, and the pixel's elevation angle (/ π/2), so the
network knows where on the sphere it looks as the boosted variant does. Pixels without a
label (unlabelled, no point, class 7) are ignored by the loss. The weights are kept as
numpy arrays, so a saved model loads without torch.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.image.config import ImageConfig
from semantic3d.baselines.image.faces import Face
from semantic3d.core.errors import require

__all__ = ["UNetSegmenter", "build_unet"]

_IGNORE = -1


def build_unet(n_inputs: int, n_classes: int, *, base_channels: int, depth: int) -> Any:
    """A U-Net ``nn.Module``: ``depth`` levels, ``base_channels`` doubled per level."""
    torch: Any = require("torch", "torch")
    nn = torch.nn

    def block(cin: int, cout: int) -> Any:
        return nn.Sequential(
            nn.Conv2d(cin, cout, 3, padding=1),
            nn.BatchNorm2d(cout),
            nn.ReLU(inplace=True),
            nn.Conv2d(cout, cout, 3, padding=1),
            nn.BatchNorm2d(cout),
            nn.ReLU(inplace=True),
        )

    class UNet(nn.Module):  # type: ignore[name-defined]
        def __init__(self) -> None:
            super().__init__()
            widths = [base_channels * 2**level for level in range(depth + 1)]
            self.down = nn.ModuleList(
                [block(n_inputs, widths[0])]
                + [block(widths[i], widths[i + 1]) for i in range(depth)]
            )
            self.up = nn.ModuleList(
                [nn.ConvTranspose2d(widths[i + 1], widths[i], 2, stride=2) for i in range(depth)]
            )
            self.merge = nn.ModuleList([block(2 * widths[i], widths[i]) for i in range(depth)])
            self.head = nn.Conv2d(widths[0], n_classes, 1)

        def forward(self, x: Any) -> Any:
            skips = []
            for level, layer in enumerate(self.down):
                if level:
                    x = torch.nn.functional.max_pool2d(x, 2)
                x = layer(x)
                skips.append(x)
            for level in reversed(range(depth)):
                x = self.up[level](x)
                x = self.merge[level](torch.cat([skips[level], x], dim=1))
            return self.head(x)

    return UNet()


def _inputs(face: Face) -> NDArray[np.float32]:
    return np.concatenate(
        [
            np.moveaxis(face.rgb.astype(np.float32) / 255.0, -1, 0),
            face.valid[None].astype(np.float32),
            face.elevation[None] / (math.pi / 2),
        ]
    ).astype(np.float32)


class UNetSegmenter:
    """U-Net on cube faces; ``fit`` returns self, fitted attributes end in ``_``.

    Attributes:
        classes_: label values it predicts.
        loss_history_: mean training loss (weighted cross-entropy) of each epoch, to see
            whether training has converged.
    """

    def __init__(self, config: ImageConfig) -> None:
        self.config = config

    def fit(
        self, faces: Sequence[Face], *, progress: Callable[[str, int, int], None] | None = None
    ) -> UNetSegmenter:
        """Train on labelled faces (random crops, Adam, cross-entropy).

        Raises:
            ValueError: fewer than two classes among the labelled pixels.
        """
        torch: Any = require("torch", "torch")
        settings = self.config.unet
        usable = [f for f in faces if f.labels is not None and (f.labels > 0).any()]
        values = (
            np.unique(
                np.concatenate([f.labels[f.labels > 0] for f in usable if f.labels is not None])
            )
            if usable
            else np.empty(0, np.uint8)
        )
        if values.size < 2:
            raise ValueError(
                f"training faces: expected labelled pixels of at least 2 classes, found "
                f"{values.tolist()}"
            )
        self.classes_ = values.astype(np.uint8)
        lookup = np.full(256, _IGNORE, np.int64)
        lookup[self.classes_] = np.arange(self.classes_.size)
        inputs = np.stack([_inputs(f) for f in usable])
        targets = np.stack([lookup[f.labels] for f in usable if f.labels is not None])
        counts = np.bincount(targets[targets >= 0], minlength=self.classes_.size).astype(np.float64)
        weights = np.where(counts > 0, 1.0 / np.sqrt(np.maximum(counts, 1)), 0.0)
        weights = weights / weights[weights > 0].mean()
        torch.manual_seed(self.config.seed)
        rng = np.random.default_rng(self.config.seed)
        network = build_unet(
            inputs.shape[1],
            self.classes_.size,
            base_channels=settings.base_channels,
            depth=settings.depth,
        )
        optimiser = torch.optim.Adam(network.parameters(), lr=settings.learning_rate)
        loss_fn = torch.nn.CrossEntropyLoss(
            weight=torch.as_tensor(weights, dtype=torch.float32), ignore_index=_IGNORE
        )
        size = inputs.shape[-1]
        multiple = 1 << settings.depth
        crop = min(settings.crop_px, size - size % multiple)
        network.train()
        self.loss_history_: list[float] = []
        for epoch in range(settings.epochs):
            order = rng.permutation(len(usable))
            losses: list[float] = []
            for begin in range(0, order.size, settings.batch_size):
                batch = order[begin : begin + settings.batch_size]
                rows = rng.integers(0, size - crop + 1, batch.size)
                cols = rng.integers(0, size - crop + 1, batch.size)
                x = np.stack(
                    [
                        inputs[i, :, r : r + crop, c : c + crop]
                        for i, r, c in zip(batch, rows, cols, strict=True)
                    ]
                )
                y = np.stack(
                    [
                        targets[i, r : r + crop, c : c + crop]
                        for i, r, c in zip(batch, rows, cols, strict=True)
                    ]
                )
                if not (y >= 0).any():
                    continue
                optimiser.zero_grad()
                loss = loss_fn(network(torch.from_numpy(x)), torch.from_numpy(y))
                loss.backward()
                optimiser.step()
                losses.append(float(loss.detach()))
            self.loss_history_.append(float(np.mean(losses)) if losses else float("nan"))
            if progress is not None:
                progress("epochs", epoch + 1, settings.epochs)
        self.n_inputs_ = int(inputs.shape[1])
        self.state_ = {k: v.detach().cpu().numpy().copy() for k, v in network.state_dict().items()}
        self._network: Any = None
        return self

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_network"] = None
        return state

    def _model(self) -> Any:
        torch: Any = require("torch", "torch")
        if getattr(self, "_network", None) is None:
            settings = self.config.unet
            network = build_unet(
                self.n_inputs_,
                self.classes_.size,
                base_channels=settings.base_channels,
                depth=settings.depth,
            )
            network.load_state_dict({k: torch.from_numpy(v) for k, v in self.state_.items()})
            network.eval()
            self._network = network
        return self._network

    def predict_proba(self, face: Face) -> NDArray[np.float32]:
        """``(s, s, n_classes)`` softmax of the network."""
        torch: Any = require("torch", "torch")
        x = _inputs(face)
        size = x.shape[-1]
        multiple = 1 << self.config.unet.depth
        padded = -size % multiple
        x = np.pad(x, ((0, 0), (0, padded), (0, padded)))
        with torch.no_grad():
            logits = self._model()(torch.from_numpy(x[None]))
            proba = torch.softmax(logits, dim=1)[0, :, :size, :size].numpy()
        return np.moveaxis(proba, 0, -1).astype(np.float32)

    def segment(self, face: Face) -> NDArray[np.uint8]:
        """``(s, s)`` label values (0 where no point is shown)."""
        labels = self.classes_[np.argmax(self.predict_proba(face), axis=-1)]
        labels[~face.valid] = 0
        return labels
