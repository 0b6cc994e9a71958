"""Output files: never written onto an input, never replacing a file without `overwrite`, and
never seen half-written (staged in the same folder, then moved into place with os.replace).

Every command that writes files goes through here: `check_output` before the work starts (a
refusal costs nothing), `staged` or `write_text`/`write_bytes` for the writing itself.
"""

from __future__ import annotations

import io
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterable, Iterator

from .errors import OutputPathError

PathLike = str | os.PathLike


def same_file(a: PathLike, b: PathLike) -> bool:
    """True when `a` and `b` are one file (same device and inode: symlinks and hard links too)."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist: they cannot be the same file
        return False


def check_output(path: PathLike, inputs: Iterable[PathLike] = (), overwrite: bool = False) -> Path:
    """The path to write for output `path` (symlinks resolved, so a link keeps pointing at the
    new file); raises OutputPathError when it is one of `inputs` (even with `overwrite`), a
    folder, or an existing file and `overwrite` is false."""
    out = Path(path)
    for inp in inputs:
        if same_file(out, inp):
            what = "the input" if os.path.abspath(out) == os.path.abspath(inp) else f"the same file as the input {inp}"
            raise OutputPathError(f"{out}: the output is {what}: refusing to write onto it (choose another output)")
    if out.is_dir():
        raise OutputPathError(f"{out}: the output is a folder, not a file")
    if os.path.lexists(out) and not overwrite:
        raise OutputPathError(f"{out}: exists; refusing to replace it (pass --overwrite to replace it)")
    return Path(os.path.realpath(out))


@contextmanager
def staged(path: PathLike, inputs: Iterable[PathLike] = (), overwrite: bool = False) -> Iterator[Path]:
    """Yield `FOLDER/.vmocap-XXXX/NAME` for output `FOLDER/NAME`: write it (and any sibling
    files, e.g. BVH parts) there under their final names. When the block ends normally every
    file of the staging folder is checked (check_output) and moved next to `path`; when it
    raises, or any move would be refused, nothing is moved and the staging folder is removed."""
    inputs = list(inputs)
    final = check_output(path, inputs, overwrite)
    final.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".vmocap-", dir=final.parent))
    try:
        yield stage / final.name
        files = sorted(p for p in stage.iterdir() if p.is_file())
        targets = [check_output(final.parent / p.name, inputs, overwrite) for p in files]
        for src, dst in zip(files, targets):
            _sync(src)
            os.replace(src, dst)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def write_bytes(path: PathLike, data: bytes, inputs: Iterable[PathLike] = (), overwrite: bool = False) -> Path:
    """Write `data` to `path` atomically (see `staged`); returns the path written."""
    with staged(path, inputs, overwrite) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path: PathLike, text: str, inputs: Iterable[PathLike] = (), overwrite: bool = False) -> Path:
    """Write `text` (UTF-8) to `path` atomically (see `staged`); returns the path written."""
    return write_bytes(path, text.encode(), inputs, overwrite)


def output_folder(folder: PathLike, names: Iterable[str] = (), inputs: Iterable[PathLike] = ()) -> Path:
    """Create the explicitly named `folder` for a command's own files (plots): those files
    (`names`, when known ahead) replace the command's earlier ones there, but never an input
    (OutputPathError, raised before anything is written, as for a folder that is a file)."""
    out = Path(folder)
    if os.path.lexists(out) and not out.is_dir():
        raise OutputPathError(f"{out}: exists and is not a folder")
    inputs = list(inputs)
    for name in names:
        check_output(out / name, inputs, overwrite=True)
    out.mkdir(parents=True, exist_ok=True)
    return out


def write_figure(fig: Any, path: PathLike, inputs: Iterable[PathLike] = (), overwrite: bool = True, **savefig: Any) -> Path:
    """A matplotlib figure as `path` (format from its suffix), atomically (see `staged`);
    overwrite defaults to true: figures go into a folder the user named for them."""
    buf = io.BytesIO()
    fig.savefig(buf, format=Path(path).suffix.lstrip(".") or "png", **savefig)
    return write_bytes(path, buf.getvalue(), inputs, overwrite)


def _sync(path: Path) -> None:
    """Flush a finished file to disk before it replaces anything: after a crash the rename
    must not point at data still in the page cache."""
    with open(path, "rb") as f:
        os.fsync(f.fileno())
