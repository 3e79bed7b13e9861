"""`wait_until` answers truthy iff the condition held, and says what it waited for."""

from __future__ import annotations

import itertools

from services.tools.cell.wait import wait_until


def test_a_condition_that_holds_is_truthy_and_named() -> None:
    calls = itertools.count()
    waited = wait_until(lambda: next(calls) >= 3, 5.0, 0.001, what="three polls")
    assert waited
    assert waited.held and waited.elapsed_s < 5.0
    assert repr(waited).startswith("<three polls held after ")


def test_a_timeout_is_falsy_and_names_the_condition_and_the_deadline() -> None:
    def never() -> bool:
        return False

    waited = wait_until(never, 0.05, 0.01)
    assert not waited
    assert waited.elapsed_s >= 0.05
    assert repr(waited).startswith("<timed out: ")
    assert repr(waited).endswith(".<locals>.never still false after 0.05 s>")


def test_a_lambda_is_named_by_where_it_was_written() -> None:
    waited = wait_until(lambda: False, 0.0)
    assert "lambda at test_wait.py:" in repr(waited)


def test_a_late_truth_at_the_deadline_is_not_missed() -> None:
    answers = iter([False, True])
    assert wait_until(lambda: next(answers), 0.0, 0.01)
