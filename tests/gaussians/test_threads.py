"""The render threads' shared work board: every task runs once, idle threads take part, errors reach
their owner."""

from __future__ import annotations

import threading
import time

import pytest

from twinbench.gaussians.threads import WorkBoard, run_threads


def test_work_board_runs_each_task_once_and_idle_threads_help():
    board = WorkBoard(owners=2)
    ran: list[tuple[str, int, str]] = []
    lock = threading.Lock()

    def task(owner: str, k: int):
        def run():
            time.sleep(0.002)
            with lock:
                ran.append((owner, k, threading.current_thread().name))
        return run

    def long_owner():  # shares 40 tasks after a while
        try:
            time.sleep(0.01)
            board.share([task("long", k) for k in range(40)])
        finally:
            board.finish()
        board.help()

    def short_owner():  # shares nothing, then helps
        board.finish()
        board.help()

    run_threads([long_owner, short_owner])
    assert sorted(k for _, k, _ in ran) == list(range(40))
    assert len({name for _, _, name in ran}) == 2  # the idle thread took some of them


def test_work_board_reraises_a_helpers_error_in_the_owner():
    board = WorkBoard(owners=2)
    errors: list[BaseException] = []

    def bad():
        raise RuntimeError("tile 7 failed")

    def owner():
        try:
            board.share([lambda: time.sleep(0.005)] * 5 + [bad] + [lambda: None] * 5)
        except RuntimeError as exc:
            errors.append(exc)
        finally:
            board.finish()
        board.help()

    def helper():
        board.finish()
        board.help()

    run_threads([owner, helper])
    assert len(errors) == 1 and "tile 7" in str(errors[0])
    with pytest.raises(RuntimeError, match="tile 7"):  # alone: the owner runs every task itself
        WorkBoard(owners=1).share([bad])
