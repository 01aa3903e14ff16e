"""`PairDataset`: stored pairs rendered on the fly as torch tensors."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from numpy.typing import NDArray
from torch.utils.data import Dataset

from scanguard.dataset.store import PairStore
from scanguard.detect.images import augment_pair
from scanguard.detect.render import RenderStyle, render_pair


class PairDataset(Dataset[tuple[torch.Tensor, torch.Tensor]]):
    """Pairs of a `PairStore` rendered in any `RenderStyle`, optionally augmented.

    Items are ``(image float32 C×H×W in [0, 1], label int64)``; the label is the stored one
    (ambiguous pairs return -1, which is why the default index set leaves them out).
    Augmentation is deterministic for a given ``seed``, epoch (`set_epoch`) and index.

    Args:
        store: The pair store.
        indices: Pair indices (None = every non-ambiguous pair of every split).
        style: Render style (default: the paper's 256x256 RGB).
        augment: Rotate the whole pair about the previous sensor origin and drop points.
        seed: Augmentation seed.
        rotation_deg: Maximum augmentation rotation (deg).
        dropout: Point dropout probability of the augmentation.
    """

    def __init__(
        self,
        store: PairStore,
        indices: Sequence[int] | NDArray[np.integer] | None = None,
        style: RenderStyle | None = None,
        augment: bool = False,
        seed: int = 0,
        *,
        rotation_deg: float = 180.0,
        dropout: float = 0.1,
    ) -> None:
        self.store = store
        self.indices = store.indices() if indices is None else np.asarray(indices, dtype=np.int64)
        self.style = style or RenderStyle.paper()
        self.augment = augment
        self.seed = seed
        self.rotation_deg = rotation_deg
        self.dropout = dropout
        self.epoch = 0

    def __len__(self) -> int:
        return int(self.indices.size)

    def set_epoch(self, epoch: int) -> None:
        """Change the augmentation draw (call once per training epoch)."""
        self.epoch = int(epoch)

    @property
    def labels(self) -> NDArray[np.int8]:
        """Labels of the items, in item order."""
        return self.store.records["label"][self.indices]

    def image(self, k: int) -> NDArray[np.uint8]:
        """Item ``k`` as a uint8 ``(H, W, C)`` image."""
        i = int(self.indices[k])
        prev, cur, est = self.store.pair_points(i)
        if self.augment:
            rng = np.random.default_rng((self.seed, self.epoch, i))
            prev, cur, est = augment_pair(
                prev, cur, est, rng, rotation_deg=self.rotation_deg, dropout=self.dropout
            )
        return render_pair(prev, cur, est, self.style)

    def __getitem__(self, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        img = self.image(k)
        x = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1))).float().div_(255.0)
        y = torch.tensor(int(self.store.records["label"][int(self.indices[k])]), dtype=torch.int64)
        return x, y
