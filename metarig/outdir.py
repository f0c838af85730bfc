"""Output folders written whole or not at all.

A command that writes a folder of files (a run folder) writes them into a hidden sibling
`.NAME.PID.part` and renames it to NAME when everything is written; any error or Ctrl-C removes
the sibling, so NAME either does not exist or holds a complete result. The rename is atomic
within one file system (the sibling lies beside NAME for that reason).
"""

import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class OutputExistsError(ValueError):
    """The output folder already holds files (the message names it)."""


def check_free(out: str | Path, flag: str = "--out") -> Path:
    """`out` as a Path, if it does not exist or is an empty folder.

    Raises:
        OutputExistsError: it is a file or a folder with something in it.
    """
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise OutputExistsError(f"{flag} {out} exists and is not empty; choose another "
                                "folder or remove it")
    return out


@contextmanager
def staged_folder(out: str | Path, flag: str = "--out") -> Iterator[Path]:
    """Yield a fresh hidden sibling of `out` to write into; rename it to `out` on success,
    remove it on any exception (KeyboardInterrupt included).

    Raises:
        OutputExistsError: `out` is not free (`check_free`), before anything is written.
    """
    out = check_free(out, flag)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.{os.getpid()}.part"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        yield tmp
        check_free(out, flag)  # nothing appeared there meanwhile
        if out.exists():
            out.rmdir()
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
