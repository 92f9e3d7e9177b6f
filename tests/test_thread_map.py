"""`twin.lanes.thread_map`: a diagnosis's per-candidate stages on threads give what one after another gives."""

import threading
import time

import pytest

from twin.lanes import thread_map


def test_results_come_in_order_from_several_threads_and_a_failure_is_raised() -> None:
    seen = set()

    def slow_square(k: int) -> int:
        seen.add(threading.get_ident())
        time.sleep(0.02 * (5 - k))  # the first items end last
        return k * k

    assert thread_map(slow_square, list(range(5)), workers=3) == [0, 1, 4, 9, 16]
    assert len(seen) > 1  # ran on more than one thread
    seen.clear()
    assert thread_map(slow_square, [2, 3], workers=1) == [4, 9] and seen == {threading.get_ident()}
    assert thread_map(slow_square, []) == []

    def fails_on_three(k: int) -> int:
        if k == 3:
            raise ValueError("three")
        return k

    with pytest.raises(ValueError, match="three"):
        thread_map(fails_on_three, list(range(6)), workers=2)
