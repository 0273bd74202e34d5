"""Output-path checks made before a command starts work, and the command line's last line
of defence against the operating system's refusals."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from arcade import cli
from arcade_io.runs import OutputPathError, check_output_dir, check_output_file

#: A folder in which nobody can create anything, root included (permission bits are no
#: guard for root: only an attempt tells).
UNWRITABLE = Path("/proc")


def test_a_folder_that_can_be_made_passes_and_is_not_made(tmp_path):
    target = tmp_path / "a" / "b"
    assert check_output_dir(target) == target
    assert not (tmp_path / "a").exists()
    assert list(tmp_path.iterdir()) == []  # the write probe left nothing behind


def test_an_existing_writable_folder_passes_and_is_left_as_it_was(tmp_path):
    (tmp_path / "kept.txt").write_text("x")
    assert check_output_dir(tmp_path) == tmp_path
    assert [p.name for p in tmp_path.iterdir()] == ["kept.txt"]


def test_a_file_where_a_folder_is_asked_is_refused(tmp_path):
    f = tmp_path / "f"
    f.write_text("x")
    with pytest.raises(OutputPathError, match="existing file, not a folder"):
        check_output_dir(f, "--out")
    with pytest.raises(OutputPathError, match="is a file, not a folder"):
        check_output_dir(f / "below", "--out")


@pytest.mark.skipif(not UNWRITABLE.is_dir(), reason="needs Linux's /proc")
def test_a_folder_the_system_refuses_is_refused_even_for_root():
    with pytest.raises(OutputPathError, match=r"--out /proc/x: cannot write in /proc"):
        check_output_dir(UNWRITABLE / "x", "--out")
    with pytest.raises(OutputPathError, match="cannot write in /proc"):
        check_output_file(UNWRITABLE / "out.json", "--out")


def test_a_file_in_a_folder_that_can_be_made_passes(tmp_path):
    assert check_output_file(tmp_path / "new" / "r.json") == tmp_path / "new" / "r.json"
    assert not (tmp_path / "new").exists()
    d = tmp_path / "d"
    d.mkdir()
    with pytest.raises(OutputPathError, match="existing folder; give a file name"):
        check_output_file(d)


def test_an_os_refusal_in_a_command_is_one_error_line(monkeypatch, capsys):
    def refuse(args):
        raise OSError(errno.ENOSPC, "No space left on device", "/data/run/results.json")

    monkeypatch.setattr(cli, "build_parser", lambda: _parser_running(refuse))
    assert cli.main(["go"]) == 1
    err = capsys.readouterr().err
    assert err == "error: No space left on device: /data/run/results.json\n"


def test_os_error_text_names_both_files_of_a_rename():
    exc = OSError(errno.EXDEV, "Invalid cross-device link", "/a/tmp", None, "/b/out")
    assert cli.os_error_text(exc) == "Invalid cross-device link: /a/tmp -> /b/out"
    assert cli.os_error_text(OSError("plain")) == "plain"


def _parser_running(fn):
    import argparse

    p = argparse.ArgumentParser()
    p.add_argument("cmd")
    p.set_defaults(_run=fn)
    return p
