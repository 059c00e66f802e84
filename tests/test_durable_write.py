"""ebrl.durable, the one way files are written durably: what lands, with which mode, what a failure leaves, and the
order of fsyncs and renames that makes a crash leave the old file or the whole new one."""

from __future__ import annotations

import ast
import contextlib
import errno
import os
import stat
import sys

import pytest

from ebrl import durable
from helpers import ROOT


@contextlib.contextmanager
def umask(mask: int):
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


def mode_of(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def others(directory, *names) -> list[str]:
    """What is in ``directory`` besides ``names``: a stray temporary shows here."""
    return sorted(set(os.listdir(directory)) - set(names))


class Steps:
    """Records the fsyncs (of a file or of a directory), renames and links, in order (os's functions are the
    boundary: the disk's own order is not observable in a test)."""

    def __init__(self, monkeypatch):
        self.steps: list[tuple[str, str]] = []
        real_fsync, real_replace, real_link = os.fsync, os.replace, os.link

        def fsync(fd):
            kind = "fsync dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "fsync file"
            self.steps.append((kind, os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))))
            return real_fsync(fd)

        def replace(src, dst):
            self.steps.append(("replace", os.path.basename(dst)))
            return real_replace(src, dst)

        def link(src, dst):
            self.steps.append(("link", os.path.basename(dst)))
            return real_link(src, dst)

        monkeypatch.setattr(os, "fsync", fsync)
        monkeypatch.setattr(os, "replace", replace)
        monkeypatch.setattr(os, "link", link)

    def kinds(self) -> list[str]:
        return [kind for kind, _ in self.steps]


def test_the_content_lands_and_replaces_the_old_file_with_nothing_left_beside_it(tmp_path):
    path = tmp_path / "state.json"
    assert durable.write_bytes(path, b"old") == path
    durable.write_text(str(path), "new \u00e9\n")  # a str path too
    assert path.read_text(encoding="utf-8") == "new \u00e9\n" and others(tmp_path, "state.json") == []


def test_the_mode_is_what_the_umask_allows_unless_a_private_one_is_asked_for(tmp_path):
    with umask(0o022):
        assert mode_of(durable.write_text(tmp_path / "a", "x")) == 0o644  # as a plain open() makes it
        assert mode_of(durable.write_text(tmp_path / "secret", "x", mode=0o600)) == 0o600
        assert mode_of(durable.write_text(tmp_path / "new", "x", mode=0o600, exclusive=True)) == 0o600
        with durable.writing(tmp_path / "b") as tmp:  # a writer that puts a private file of its own there
            own = tmp_path / "own"                   # (safetensors' save_file does)
            os.close(os.open(own, os.O_WRONLY | os.O_CREAT, 0o600))
            os.rename(own, tmp)
        assert mode_of(tmp_path / "b") == 0o644
    with umask(0o002):
        assert mode_of(durable.write_text(tmp_path / "c", "x")) == 0o664
    (tmp_path / "secret").chmod(0o644)
    durable.write_text(tmp_path / "secret", "y", mode=0o600)  # the new file's mode, not the old one's
    assert mode_of(tmp_path / "secret") == 0o600


def test_an_exclusive_write_refuses_an_existing_file_and_leaves_it_intact(tmp_path):
    path = tmp_path / "bus.secret"
    durable.write_text(path, "first\n", mode=0o600, exclusive=True)
    with pytest.raises(FileExistsError) as refused:
        durable.write_text(path, "second\n", mode=0o600, exclusive=True)
    with pytest.raises(FileExistsError) as excl:
        os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    assert str(refused.value) == str(excl.value)  # the message O_EXCL gives: "[Errno 17] File exists: '...'"
    assert path.read_text() == "first\n" and others(tmp_path, "bus.secret") == []


def test_an_exclusive_write_where_the_disk_has_no_hard_links_creates_the_file_in_place(tmp_path, monkeypatch):
    def no_links(src, dst):
        raise PermissionError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(os, "link", no_links)
    path = durable.write_text(tmp_path / "bus.secret", "first\n", mode=0o600, exclusive=True)
    assert path.read_text() == "first\n" and mode_of(path) == 0o600
    with pytest.raises(FileExistsError):
        durable.write_text(path, "second\n", exclusive=True)
    assert path.read_text() == "first\n" and others(tmp_path, "bus.secret") == []


class Failed(Exception):
    pass


def test_a_writer_that_fails_leaves_no_target_and_no_temporary(tmp_path):
    path = tmp_path / "policy.safetensors"
    with pytest.raises(Failed), durable.writing(path) as tmp:
        tmp.write_bytes(b"half")
        raise Failed
    assert others(tmp_path) == []
    path.write_bytes(b"old")
    with pytest.raises(Failed), durable.writing(path) as tmp:
        raise Failed
    assert path.read_bytes() == b"old" and others(tmp_path, path.name) == []


def test_a_failed_rename_or_link_leaves_no_temporary(tmp_path, monkeypatch):
    def full(*args):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "replace", full)
    with pytest.raises(OSError, match="No space"):
        durable.write_text(tmp_path / "meta.json", "{}")
    monkeypatch.setattr(os, "link", full)
    with pytest.raises(OSError, match="No space"):
        durable.write_text(tmp_path / "bus.secret", "x", exclusive=True)
    assert others(tmp_path) == []


def test_the_file_is_fsynced_before_its_rename_and_the_directory_after_it(tmp_path, monkeypatch):
    steps = Steps(monkeypatch)
    durable.write_text(tmp_path / "latest", "v00000001\n")
    (kind, tmp), renamed, dir_synced = steps.steps
    assert (kind, renamed, dir_synced) == ("fsync file", ("replace", "latest"), ("fsync dir", tmp_path.name))
    assert tmp.startswith(".latest.") and tmp.endswith(".tmp")  # beside it, hidden, found by temporaries()
    steps.steps.clear()
    durable.write_text(tmp_path / "bus.secret", "x", mode=0o600, exclusive=True)
    assert steps.kinds() == ["fsync file", "link", "fsync dir"]


def test_replace_dir_syncs_everything_in_it_then_puts_it_in_place_of_the_old_one(tmp_path, monkeypatch):
    tmp, final = tmp_path / "v00000002.tmp", tmp_path / "v00000002"
    final.mkdir()
    (final / "stale").write_text("from an earlier write of the same version")
    (tmp / "deep").mkdir(parents=True)
    for name in ("policy.safetensors", "state.json", "deep/x"):
        (tmp / name).write_text(name)
    steps = Steps(monkeypatch)
    durable.replace_dir(tmp, final)
    assert sorted(str(p.relative_to(final)) for p in final.rglob("*")) == ["deep", "deep/x", "policy.safetensors",
                                                                         "state.json"]
    assert not tmp.exists() and (final / "state.json").read_text() == "state.json"
    *inside, renamed, parent = steps.steps
    assert sorted(name for kind, name in inside if kind == "fsync file") == ["policy.safetensors", "state.json", "x"]
    assert inside[-1] == ("fsync dir", tmp.name)  # the directory itself last, with every file in it
    assert renamed == ("replace", final.name) and parent == ("fsync dir", tmp_path.name)


def test_replace_dir_puts_a_new_directory_in_place(tmp_path):
    tmp = tmp_path / "v1.tmp"
    tmp.mkdir()
    (tmp / "a").write_text("a")
    durable.replace_dir(tmp, tmp_path / "v1")
    assert os.listdir(tmp_path) == ["v1"] and (tmp_path / "v1" / "a").read_text() == "a"


def test_temporaries_are_a_files_own_leftovers_oldest_first_and_removed_on_request(tmp_path):
    path = tmp_path / "train-pending.msgpack"
    older, newer = tmp_path / ".train-pending.msgpack.a1.tmp", tmp_path / ".train-pending.msgpack.b2.tmp"
    newer.write_bytes(b"2")
    older.write_bytes(b"1")
    os.utime(older, (1, 1))
    (tmp_path / ".policy.safetensors.c3.tmp").write_bytes(b"another file's")
    (tmp_path / "train-pending.msgpack.tmp").write_bytes(b"not this module's name")
    assert durable.temporaries(path) == [older, newer]
    assert durable.remove_temporaries(str(path)) == [older, newer] and durable.temporaries(path) == []
    assert others(tmp_path) == [".policy.safetensors.c3.tmp", "train-pending.msgpack.tmp"]


# What may still rename or fsync outside ebrl/durable.py, and why it is not a durable write of a file.
NOT_DURABLE_WRITES = {
    ("ebrl/bus/auth.py", "os.fsync"): "ensure appends the identities an older secret file lacks, keeping its lines",
    ("ebrl/algos/checkpoint.py", "os.replace"): "an old checkpoint leaves the v* names before it is deleted",
    ("ebrl/evaluate.py", "os.replace"): "a video imageio streams to a name that keeps its format (<stem>.tmp.mp4)",
}


def test_files_are_written_durably_only_through_ebrl_durable_which_needs_only_the_standard_library():
    """One writer of durable files (issue 56: "two modules write checkpoints"): no other module renames files into
    place, fsyncs or makes temporaries itself, except the few named above; and ebrl.durable, the bottom layer,
    imports nothing of ebrl or outside the standard library."""
    calls = {"os": {"replace", "rename", "fsync", "link"}, "tempfile": {"mkstemp"}}
    found = set()
    for path in sorted((ROOT / "ebrl").rglob("*.py")):
        name = str(path.relative_to(ROOT))
        if name == "ebrl/durable.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                    and isinstance(node.func.value, ast.Name) and node.func.attr in calls.get(node.func.value.id, ()):
                found.add((name, f"{node.func.value.id}.{node.func.attr}"))
    outside = sorted(found - NOT_DURABLE_WRITES.keys())
    assert not outside, f"write these through ebrl.durable: {outside}"
    tree = ast.parse((ROOT / "ebrl" / "durable.py").read_text())
    imported = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import)
                for alias in node.names}
    imported |= {node.module.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
                 and node.module and node.module != "__future__"}
    assert imported <= sys.stdlib_module_names, imported - sys.stdlib_module_names
