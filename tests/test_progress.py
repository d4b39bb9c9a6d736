"""progress.csv followed as the learner writes it (`learner.progress.ProgressFollower`): what the distributed
Python API hands its callback, row by row, without reading the file again each time."""

from __future__ import annotations

import os

from silcr.common import run_layout
from silcr.learner.progress import ProgressFollower

HEADER = "time,env_steps,eval_return\n"


def _append(path, text: str) -> None:
    with open(path, "a") as f:
        f.write(text)


def test_each_row_is_given_once_and_only_when_its_line_has_ended(tmp_path):
    path = run_layout.progress(tmp_path)
    follower = ProgressFollower(tmp_path)  # before the learner wrote anything
    assert follower.new_rows() == []
    _append(path, HEADER + "1.0,0,5.5\n2.0,1000,")
    assert follower.new_rows() == [{"time": "1.0", "env_steps": "0", "eval_return": "5.5"}]
    assert follower.new_rows() == []  # the second row is half-written
    _append(path, "7.25\n3.0,2000,9\n")
    assert [r["env_steps"] for r in follower.new_rows()] == ["1000", "2000"]
    assert follower.new_rows() == []
    assert follower.offset == os.path.getsize(path)  # read from where it stopped, not from the start


def test_rows_written_before_it_started_are_not_given_again(tmp_path):
    path = run_layout.progress(tmp_path)
    _append(path, HEADER + "1.0,0,5.5\n2.0,1000,7\n")  # a resumed run's earlier rows
    follower = ProgressFollower(tmp_path)
    assert follower.new_rows() == []
    _append(path, "3.0,2000,9\n")
    assert follower.new_rows() == [{"time": "3.0", "env_steps": "2000", "eval_return": "9"}]


def test_a_file_rewritten_in_place_is_read_again_without_repeating_rows(tmp_path):
    path = run_layout.progress(tmp_path)
    _append(path, HEADER + "1.0,0,5.5\n2.0,1000,7\n")
    follower = ProgressFollower(tmp_path)
    tmp = tmp_path / "progress.csv.tmp"
    tmp.write_text(HEADER + "1.0,0,5.5\n2.0,1000,7\n3.0,2000,9\n")
    tmp.replace(path)  # a new file (another inode): read from its start, the two rows given before skipped
    assert follower.new_rows() == [{"time": "3.0", "env_steps": "2000", "eval_return": "9"}]
    assert follower.new_rows() == []
