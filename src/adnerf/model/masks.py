"""Per-frame pixel masks stored eight pixels to a byte.

Training keeps a few boolean masks for every frame of a clip (which pixels' rays cross the head
box, where the torso may reach behind the chin). As ``bool`` tensors each costs a byte a pixel, a
third of the clip's uint8 frames; packed, an eighth of a byte. :class:`BitRows` holds ``N`` masks
of ``L`` pixels and reads them back whole (:meth:`BitRows.row`) or at single pixels of any frames
(:meth:`BitRows.at`, a gather that never unpacks a frame).

Bit ``j`` of byte ``k`` of a row is pixel ``8 k + j``.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["BitRows"]


class BitRows:
    """``n`` boolean rows of ``length`` entries, packed into ``(n, ceil(length / 8))`` uint8.

    Args:
        n: Number of rows (frames).
        length: Entries per row (pixels).
        device: Where the bytes live.
    """

    def __init__(self, n: int, length: int, device: torch.device | str | None = None) -> None:
        if n < 0 or length < 0:
            raise ValueError(f"BitRows needs n >= 0 and length >= 0; got {n}, {length}")
        self.n, self.length = n, length
        self.bytes = torch.zeros(n, (length + 7) // 8, dtype=torch.uint8, device=device)
        self._shifts = torch.arange(8, dtype=torch.uint8, device=device)

    @property
    def nbytes(self) -> int:
        """Bytes held."""
        return self.bytes.numel()

    def set(self, rows: int | slice | Tensor, masks: Tensor) -> None:
        """Store ``masks`` ``(length,)`` (or ``(k, length)`` for a slice or index tensor of ``k``
        rows), bool."""
        m = masks.reshape(-1, self.length).to(device=self.bytes.device, dtype=torch.uint8)
        pad = self.bytes.shape[1] * 8 - self.length
        if pad:
            m = torch.cat([m, m.new_zeros(len(m), pad)], dim=1)
        packed = (m.reshape(len(m), -1, 8) << self._shifts).sum(dim=2, dtype=torch.uint8)
        self.bytes[rows] = packed[0] if isinstance(rows, int) else packed

    def row(self, row: int) -> Tensor:
        """Row ``row`` unpacked, ``(length,)`` bool."""
        bits = (self.bytes[row, :, None] >> self._shifts) & 1
        return bits.reshape(-1)[: self.length].bool()

    def at(self, rows: int | Tensor, index: Tensor) -> Tensor:
        """Entries ``index`` ``(R,)`` of row ``rows`` (one row, or each entry's row ``(R,)``), bool ``(R,)``."""
        byte = self.bytes[rows, index // 8]
        return ((byte >> (index % 8).to(torch.uint8)) & 1).bool()
