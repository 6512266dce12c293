"""Progress off a terminal: a line now and then, nothing for a short run."""

from workbench.progress import duration, progress, progress_lines


def test_lines_come_once_a_minute_with_the_time_left(capsys):
    ticks = iter([0.0, 30.0, 61.0, 90.0, 125.0, 130.0])  # the start, then after each item
    out = list(progress_lines(range(5), "classification", 5, 60.0, clock=lambda: next(ticks)))
    assert out == [0, 1, 2, 3, 4]
    assert capsys.readouterr().err.splitlines() == [
        "classification: 2 of 5 (40 %) in 1 min 01 s, about 1 min 32 s left",
        "classification: 4 of 5 (80 %) in 2 min 05 s, about 31 s left",
    ]


def test_a_short_run_off_a_terminal_prints_nothing(capsys):
    assert list(progress(iter(range(1000)), "tiles")) == list(range(1000))
    assert capsys.readouterr().err == ""  # pytest's stderr is not a terminal: no bar either


def test_durations():
    assert [duration(s) for s in (0.4, 59.6, 61, 3599, 3600, 7325)] == [
        "0 s", "1 min 00 s", "1 min 01 s", "59 min 59 s", "1 h 00 min", "2 h 02 min",
    ]  # fmt: skip
