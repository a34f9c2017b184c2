"""Packed per-frame masks (:mod:`adnerf.model.masks`) read back exactly as the bool masks stored."""

from __future__ import annotations

import pytest
import torch

from adnerf.model.masks import BitRows


@pytest.mark.parametrize("length", [1, 8, 13, 64, 101])
def test_packed_rows_read_back_whole_and_per_entry(length: int) -> None:
    g = torch.Generator().manual_seed(length)
    dense = torch.rand(7, length, generator=g) < 0.4
    dense[0] = True  # all set and none set: every bit of a byte, and the padding left clear
    dense[1] = False
    bits = BitRows(7, length)
    bits.set(slice(0, 4), dense[:4])  # a slice of rows ...
    for i in range(4, 7):  # ... and single rows
        bits.set(i, dense[i])
    assert bits.nbytes == 7 * ((length + 7) // 8)
    assert torch.equal(torch.stack([bits.row(i) for i in range(7)]), dense)
    rows, index = torch.randint(7, (300,), generator=g), torch.randint(length, (300,), generator=g)
    assert torch.equal(bits.at(rows, index), dense[rows, index])  # each entry's own row
    assert torch.equal(bits.at(3, index), dense[3, index])  # one row
    # The padding past `length` stays clear, so a row never reads set bits it was not given.
    assert int(bits.bytes[0, -1]) == (1 << (length - 8 * (bits.bytes.shape[1] - 1))) - 1


def test_bit_order_is_pixel_8k_plus_j() -> None:
    bits = BitRows(1, 16)
    mask = torch.zeros(16, dtype=torch.bool)
    mask[[0, 9]] = True
    bits.set(0, mask)
    assert bits.bytes.tolist() == [[1, 2]]
