"""A command's output file is written whole or not at all (encoder_fleet/outputs.py), on a real file system."""

from __future__ import annotations

import os
import stat
import subprocess
import sys

import pytest

from encoder_fleet.outputs import replaced, write_file


def test_a_write_that_fails_leaves_the_file_that_was_there_and_nothing_beside_it(tmp_path):
    out = tmp_path / "report.json"
    out.write_text("the old report\n")
    with pytest.raises(RuntimeError):
        with replaced(out) as f:
            f.write("half of a new one")
            raise RuntimeError("the disk filled")
    assert out.read_text() == "the old report\n" and sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]


def test_a_replaced_file_keeps_its_mode_a_new_one_gets_the_umask_s_a_secret_is_0600(tmp_path):
    kept, new, secret = tmp_path / "kept.csv", tmp_path / "new.csv", tmp_path / "secret"
    kept.write_text("x")
    kept.chmod(0o640)
    write_file(kept, "y")
    old = os.umask(0o027)
    try:
        write_file(new, "z")
    finally:
        os.umask(old)
    write_file(secret, "s", perms=0o600)
    assert stat.S_IMODE(kept.stat().st_mode) == 0o640 and kept.read_text() == "y"
    assert stat.S_IMODE(new.stat().st_mode) == 0o640
    assert stat.S_IMODE(secret.stat().st_mode) == 0o600


def test_a_symlink_s_target_is_replaced_and_the_link_kept(tmp_path):
    target, link = tmp_path / "data.json", tmp_path / "latest.json"
    target.write_text("old")
    link.symlink_to(target)
    write_file(link, "new")
    assert link.is_symlink() and target.read_text() == "new"


def test_dev_stdout_is_written_through_stdout_in_order_with_what_the_command_prints(tmp_path):
    """`--json /dev/stdout > file`: the output goes where stdout goes, between the lines printed before and after
    it (replacing the file stdout goes to lost them, and opening it again truncated it)."""
    code = (
        "from encoder_fleet.outputs import write_file\n"
        "print('before', flush=True)\n"
        "write_file('/dev/stdout', 'the output\\n')\n"
        "print('after')\n"
    )
    out = tmp_path / "o.txt"
    out.write_text("kept\n")
    with open(out, "a") as f:  # >>
        subprocess.run([sys.executable, "-c", code], stdout=f, check=True)
    assert out.read_text() == "kept\nbefore\nthe output\nafter\n"
    piped = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert piped.stdout == "before\nthe output\nafter\n"
