"""Run folders are owned: wrenorm writes only into a folder it made (or an empty one), marks it, and `--force`
clears only such a marked folder, never one that holds anything else, the working directory or an input.

Callers validate every option and input first and call `prepare_out` last, so a refused command leaves the
old run untouched.
"""
from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

from .errors import InputError

MARKER = ".wrenorm-run"
LOCK = ".wrenorm-lock"  # held by the process writing the folder (hold_folder); no part of the run, kept by --force
_held: dict = {}  # folder -> open lock file, for the life of the process


def _is_run(folder: Path) -> bool:
    return (folder / MARKER).is_file()


def _guard(out: Path, inputs) -> None:
    """Folders --force must never clear: the working directory or one above it, home, the root, and any folder
    that is or holds one of the command's inputs."""
    real = out.resolve()
    cwd = Path.cwd().resolve()
    if real == cwd or real in cwd.parents:
        raise InputError(str(out), "--out", "is the working directory or a folder above it: refusing to clear it")
    if real == Path.home().resolve() or real == Path(real.anchor):
        raise InputError(str(out), "--out", "is the home or root folder: refusing to clear it")
    for item in inputs or ():
        p = Path(item).resolve()
        if p == real or real in p.parents:
            raise InputError(str(out), "--out", f"holds an input of this command ({item}): refusing to clear it")


def hold_folder(out) -> None:
    """Take the folder for this process, before prepare_out: a second sweep on the same --out (with --force, or
    --resume) while the first ran had emptied or rewritten it under the first, both saying "done" over a mix of the
    two (a probe of stop 47). Refused in one line while another process holds it; released when this one ends, also
    when it is killed. Where the platform or the file system has no advisory locks (not POSIX; Lustre mounted
    noflock), nothing is held; a folder that is not wrenorm's is left to prepare_out to refuse, untouched."""
    try:
        import fcntl
    except ImportError:
        return
    import errno

    out = Path(out)
    key = str(out.resolve())
    if key in _held:
        return
    if out.is_dir() and not _is_run(out) and any(c.name != LOCK for c in out.iterdir()):
        return  # not wrenorm's: prepare_out refuses it, and nothing may be left in it
    try:
        out.mkdir(parents=True, exist_ok=True)
        f = open(out / LOCK, "a+")
    except OSError as e:
        raise InputError(str(out), "--out", f"cannot be written: {e.strerror or e}") from None
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        if e.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):  # a file system without locks: none held
            f.close()
            return
        f.seek(0)
        who = f.read().strip()
        f.close()
        raise InputError(str(out), "--out", f"another wrenorm process is writing this folder now ({who or 'pid ?'}): "
                                            "wait for it to end, or give another --out") from None
    f.seek(0)
    f.truncate()
    f.write(f"pid {os.getpid()}, since {time.strftime('%Y-%m-%dT%H:%M:%S')}\n")
    f.flush()
    _held[key] = f


def held() -> set:
    """The folders this process holds now (hold_folder)."""
    return set(_held)


def release(keep=()) -> None:
    """Let go of the folders held, but those in `keep`: a command's holds end with the command, not with its process
    (a notebook's fit, or a sweep worker's cell, had kept its folder from every later process; review of stop 54)."""
    for key in [k for k in _held if k not in set(keep)]:
        _held.pop(key).close()


def prepare_out(out, resume: bool = False, force: bool = False, state: str | None = None, inputs=(),
                command: str = "") -> Path:
    """The run folder, ready to write into, and held by this process (hold_folder: every command, not only sweeps;
    a fit resumed while it still ran had written each generation twice into its log). Refuses to clobber an earlier
    run unless told to (--force), or continues it (--resume): a run to continue must be wrenorm's and hold its saved
    `state` file (here or in a sub-run folder)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(str(out), "--out", "exists and is not a folder")
    for parent in out.parents:
        if parent.exists() and not parent.is_dir():
            raise InputError(str(out), "--out", f"cannot be created: {parent} is a file")
    existing = out.exists() and any(c.name != LOCK for c in out.iterdir())
    if resume and force:  # one keeps the folder, the other empties it: which was meant is not ours to guess
        raise InputError(str(out), "--force", "cannot go with --resume: --resume continues the run in this folder, "
                                              "--force empties it for a new one; give one of them")
    if resume:
        if not out.exists():
            raise InputError(str(out), "--resume", "no such run folder to resume")
        if existing and not _is_run(out):
            raise InputError(str(out), "--resume", "is not a wrenorm run folder (no .wrenorm-run marker)")
        if state and not (out / state).exists() and not any(out.glob(f"*/{state}")):
            raise InputError(str(out), "--resume", f"no saved state ({state}) in this folder to resume from")
        hold_folder(out)
        return out
    if existing:
        if not force:
            raise InputError(str(out), "--out", "folder exists and is not empty; pass --force to overwrite it or "
                                                "--resume to continue it")
        if not _is_run(out):
            raise InputError(str(out), "--force", "the folder is not empty and was not written by wrenorm (no "
                                                  ".wrenorm-run marker): refusing to clear it")
        _guard(out, inputs)
        hold_folder(out)  # a --force under a run still writing the folder would empty it beneath that run
        for child in out.iterdir():
            if child.name == LOCK:
                continue
            if child.is_dir() and not child.is_symlink():
                shutil.rmtree(child)
            else:
                child.unlink()
    hold_folder(out)  # two runs started on one new --out wrote one search log between them (review of stop 54)
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / MARKER).write_text(json.dumps({"schema": "wrenorm.run/1", "command": command,
                                              "created": time.strftime("%Y-%m-%dT%H:%M:%S"), "pid": os.getpid()})
                                  + "\n")
    except OSError as e:
        raise InputError(str(out), "--out", f"cannot be written: {e.strerror or e}") from None
    return out


FIRST_NAMED = ("task", "resolutions")  # settings the others follow from (a flow's free parameters per resolution)


def check_same_settings(source: str, old: dict, new: dict, what: str = "fit") -> None:
    """A resumed run must repeat the interrupted one's settings: the first that differs (the task and resolutions
    first, then sorted by name, the sources' digest last) is an InputError naming the state file, the setting and
    both values."""
    keys = sorted((set(old) | set(new)) - {"code"}, key=lambda k: (k not in FIRST_NAMED, FIRST_NAMED.index(k)
                                                                   if k in FIRST_NAMED else 0, k))
    for key in keys:
        if old.get(key) != new.get(key):
            raise InputError(source, key, f"the interrupted {what} ran with {old.get(key)!r}, this run with "
                                          f"{new.get(key)!r}; resume with the same settings")
    if "code" in old and old["code"] != new.get("code"):  # a run saved before the digest (stop 45) has none
        raise InputError(source, "code", f"wrenorm's sources (engine, kernels or the {old.get('task', 'system')}'s "
                                         f"modules) changed since the interrupted {what} ran: finish it with the code "
                                         "it started with, or start it again")
