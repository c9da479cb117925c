"""Scene metadata points: the batched lookup gives the one-by-one values and errors."""

from __future__ import annotations

import numpy as np
import pytest

from visfly_dist.errors import ConfigError
from visfly_dist.tasks.common import metadata_point, metadata_points


def test_metadata_points_equal_the_one_by_one_lookup() -> None:
    metas = [{"goal": [9, 0.5, 1]}, {}, {"goal": np.array([[1.0, 2.0, 3.0]])}, {"goal": (4.0, -5.0, 6.25)}]
    points = metadata_points(metas, "goal", (7.0, 8.0, 9.0))
    assert points.dtype == np.float64 and points.shape == (4, 3)
    np.testing.assert_array_equal(points, [metadata_point(m, "goal", (7.0, 8.0, 9.0)) for m in metas])
    assert metadata_points([], "goal", (7.0, 8.0, 9.0)).shape == (0, 3)


@pytest.mark.parametrize("bad", [[1.0, 2.0], [1.0, float("nan"), 2.0], "abc", None, [[1.0, 2.0], [3.0]]])
def test_metadata_points_reject_what_the_one_by_one_lookup_rejects(bad: object) -> None:
    metas = [{"goal": [1.0, 2.0, 3.0]}, {"goal": bad}]
    with pytest.raises(ConfigError, match="scene metadata goal="):
        metadata_point(metas[1], "goal", (0.0, 0.0, 0.0))
    with pytest.raises(ConfigError, match="scene metadata goal="):
        metadata_points(metas, "goal", (0.0, 0.0, 0.0))
