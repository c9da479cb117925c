"""``SensorFrame.scatter``: rows written where the index says, by every path (a new frame, a buffer
of the pool, in place), whether the rows are a consecutive block (copied as one) or scattered."""

from __future__ import annotations

import pytest
import torch

from visfly_dist.client.buffer_pool import BufferPool
from visfly_dist.client.frame import SensorFrame, row_span

N = 6


def _frame(n: int, seed: int) -> SensorFrame:
    g = torch.Generator().manual_seed(seed)
    return SensorFrame(images={"depth": torch.rand(n, 1, 4, 5, generator=g),
                               "rgb": torch.randint(0, 255, (n, 3, 4, 5), generator=g, dtype=torch.uint8)},
                       collision=torch.rand(n, generator=g) > 0.5, inside=torch.rand(n, generator=g) > 0.5,
                       nearest=torch.rand(n, 3, generator=g), distance=torch.rand(n, generator=g),
                       lost=torch.rand(n, generator=g) > 0.5)


def _expected(full: SensorFrame, index: list[int], rows: SensorFrame) -> dict[str, torch.Tensor]:
    out = {k: v.clone() for k, v in {**full.images, "nearest": full.nearest, "lost": full.lost}.items()}
    for j, i in enumerate(index):
        for k, v in {**rows.images, "nearest": rows.nearest, "lost": rows.lost}.items():
            out[k][i] = v[j]
    return out


@pytest.mark.parametrize("index", [[2, 3, 4], [0], [1, 3, 4], [5, 0], [0, 2, 1, 3]],
                         ids=["block", "one", "scattered", "unordered", "a block out of order"])
@pytest.mark.parametrize("how", ["new", "buffers", "in_place"])
def test_scatter_writes_each_row_where_its_index_says(index: list[int], how: str) -> None:
    full, rows = _frame(N, 0), _frame(len(index), 1)
    before = {k: v.clone() for k, v in full.images.items()}
    expected = _expected(full, index, rows)
    merged = full.scatter(torch.tensor(index), rows, BufferPool() if how == "buffers" else None, in_place=how == "in_place")
    for k in full.images:
        torch.testing.assert_close(merged.images[k], expected[k], msg=k)
        if how == "in_place":
            assert merged.images[k] is full.images[k]
        else:  # the frame it came from is left as it was
            torch.testing.assert_close(full.images[k], before[k], msg=k)
    torch.testing.assert_close(merged.nearest, expected["nearest"])
    torch.testing.assert_close(merged.lost, expected["lost"])


def test_row_span_is_a_slice_only_for_consecutive_ascending_rows() -> None:
    assert row_span(torch.tensor([3, 4, 5])) == slice(3, 6)
    assert row_span(torch.tensor([7])) == slice(7, 8)
    assert row_span(torch.tensor([1, 3, 4])) is None
    assert row_span(torch.tensor([0, 2, 1, 3])) is None and row_span(torch.tensor([2, 1])) is None
    assert row_span(torch.tensor([], dtype=torch.long)) is None
