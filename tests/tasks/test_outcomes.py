"""End causes from step infos, in priority order."""

import pytest

from visfly_dist.tasks.outcomes import END_CAUSES, end_cause


@pytest.mark.parametrize("info, length, cause", [
    ({"is_success": True, "collision": True}, 10, "success"),
    ({"collision": True, "out_of_bounds": True}, 10, "collision"),
    ({"out_of_bounds": True}, 10, "out_of_bounds"),
    ({"lost": True, "TimeLimit.truncated": True}, 10, "lost"),
    ({"TimeLimit.truncated": False}, 10, "failure"),
    ({"TimeLimit.truncated": True}, 100, "time_limit"),
    ({"TimeLimit.truncated": True}, 40, "swapped"),
])
def test_end_cause(info, length, cause):
    assert end_cause(info, length, 100) == cause
    assert cause in END_CAUSES
