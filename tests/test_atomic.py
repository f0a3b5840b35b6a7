"""Atomic output: nothing half-written, ordinary permissions."""

from __future__ import annotations

import os
import pathlib
import stat

import pytest

from outputs.atomic import atomic_output, atomic_write, safe_name, write_text


def test_success_replaces_target_with_umask_permissions(tmp_path):
    old = os.umask(0o022)
    try:
        path = write_text(tmp_path / "out.txt", "hello")
    finally:
        os.umask(old)
    assert path.read_text() == "hello"
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_failure_leaves_existing_file_and_no_temp(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_output(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("interrupted")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_keyboard_interrupt_cleans_up(tmp_path):
    with pytest.raises(KeyboardInterrupt), atomic_output(tmp_path / "x.bin") as tmp:
        tmp.write_bytes(b"1")
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_hands_a_file_name_to_the_writer(tmp_path):
    target = tmp_path / "table.csv"
    seen = []

    def write(name: str) -> None:
        seen.append(name)
        pathlib.Path(name).write_text("a,b\n")

    assert atomic_write(target, write) == target
    assert target.read_text() == "a,b\n"
    assert seen[0] != str(target) and pathlib.Path(seen[0]).parent == tmp_path
    with pytest.raises(ValueError):
        atomic_write(target, lambda name: (pathlib.Path(name).write_text("x"), int("bad")))
    assert target.read_text() == "a,b\n"
    assert [p.name for p in tmp_path.iterdir()] == ["table.csv"]


@pytest.mark.parametrize(
    ("name", "fallback", "expected"),
    [
        ("637f20cafde22ff8", "scene", "637f20cafde22ff8"),
        ("DEU_Flensburg-10_1_T-1", "scene", "DEU_Flensburg-10_1_T-1"),
        ("a b/c:d", "scene", "a_b_c_d"),
        ("..hidden.", "scene", "hidden"),
        ("///", "record3", "record3"),
        ("", "scene", "scene"),
    ],
)
def test_safe_name(name, fallback, expected):
    assert safe_name(name, fallback) == expected
