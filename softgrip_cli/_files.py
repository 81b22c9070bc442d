"""Results -> files: output names, the output policy's checks before any work, output folders and
the ``--force`` option."""

from __future__ import annotations

import os
from pathlib import Path

from softgrip_jax import SoftgripError


def unique_png_names(scenes_paths: list[str]) -> list[str]:
    """``<frame-name>.png`` for each frame path, made unique with ``_2``, ``_3``, ... on repeats."""
    seen: dict[str, int] = {}
    names = []
    for path in scenes_paths:
        stem = Path(path).name or "frame"
        seen[stem] = seen.get(stem, 0) + 1
        names.append(f"{stem}.png" if seen[stem] == 1 else f"{stem}_{seen[stem]}.png")
    return names


def check_output_file(path: str | os.PathLike[str], what: str, inputs=(), force: bool = False) -> Path:
    """Refuse, before any work, an output file ``path`` that cannot or must not be written (the
    output policy of ``softgrip_base.atomic_write``: one of the command's ``inputs``, a folder, a FIFO or
    device, a link or read-only file without ``force``), or one whose folder does not exist or does
    not take a new file (read-only, a read-only mount: found by creating and removing an empty file
    there, as permission bits do not tell a process running as root). The message names ``what``,
    e.g. ``"-o"``, and the path."""
    from softgrip_base.atomic_write import check_output, probe_folder

    target = check_output(path, inputs=inputs, force=force, what=what)
    if not target.parent.is_dir():
        raise SoftgripError(f"{what} {path}: the folder {target.parent} does not exist (or is not a folder); "
                            f"create it first")
    probe_folder(target.parent, what=f"{what} {path}")
    return Path(path)


def frame_inputs(*folders) -> list[Path]:
    """The input files of frame ``folders`` (for the output policy)."""
    from softgrip_base.atomic_write import frame_inputs as _files

    return [path for folder in folders if folder is not None for path in _files(folder)]


def add_force_argument(parser) -> None:
    """``--force``: the output policy's permission to replace through links and read-only files."""
    parser.add_argument("--force", action="store_true",
                        help="replace an output file even when it is read-only, or a symbolic link (then the "
                             "file it points to is replaced and the link kept); inputs, folders, FIFOs and "
                             "devices are never replaced")


def ensure_dir(path: str | os.PathLike[str], what: str) -> Path:
    """Create folder ``path`` (and parents) or raise a ``SoftgripError`` naming it; refuse (an
    ``OutputRefusedError``) a folder in which no file can be created, before any work."""
    from softgrip_base.atomic_write import probe_folder

    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        from softgrip_base.input_guard import os_error_reason

        raise SoftgripError(f"cannot create the {what} {folder}: {os_error_reason(err)}") from None
    if not folder.is_dir():
        raise SoftgripError(f"the {what} {folder} is not a folder")
    probe_folder(folder, what=f"the {what} {folder}")
    return folder
