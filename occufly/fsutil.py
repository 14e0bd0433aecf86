"""Atomic file writes: write to a temporary name in the same folder, fsync, rename."""

from __future__ import annotations

import os
import re
import shutil
import struct
import tempfile
import zipfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np


def fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _process_umask() -> int:
    """The process umask, read without changing it where the OS tells it (Linux
    /proc/self/status); elsewhere set-and-restore (racy only against concurrent creators)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def ordinary_mode(*, directory: bool = False) -> int:
    """0666 (files) or 0777 (folders) minus the umask -- what open()/mkdir() would give;
    mkstemp/mkdtemp create 0600/0700, which made exports unreadable to anyone else. A
    deployment that wants its data dir private runs with umask 077."""
    return (0o777 if directory else 0o666) & ~_process_umask()


def write_tmp(path: Path, data: bytes | None = None, *, writer=None) -> Path:
    """Write a hidden, fsynced temporary sibling of ``path`` and return its name.

    Either ``data`` is written, or ``writer(file)`` is called to stream into the file.
    The caller renames it into place (``os.replace``) or removes it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, ordinary_mode())
        with os.fdopen(fd, "wb") as f:
            if writer is not None:
                writer(f)
            else:
                f.write(data)
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return Path(tmp)


def _replace_into(tmp: Path, path: Path) -> None:
    try:
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the whole new one."""
    path = Path(path)
    _replace_into(write_tmp(path, data), path)


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def atomic_save_npy(path: str | Path, array: np.ndarray) -> None:
    """np.save to ``path`` atomically (streams large arrays without an extra copy)."""
    path = Path(path)
    arr = np.asarray(array)
    _replace_into(write_tmp(path, writer=lambda f: np.save(f, arr, allow_pickle=False)), path)


def load_npz(path: str | Path, *, mmap: bool = False) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` by name. Members stored uncompressed (``np.savez``, what the
    workspace writes) are read straight into their arrays from their data's offset: no zip
    stream and no CRC pass over the bytes (33 vote files of a 20 MP review's neighbours:
    ~0.03 s of CPU instead of ~0.08-0.17 s through ``np.load``), and no file left open (a
    memory map would hold a descriptor per array while a request uses it). Any other archive
    -- a compressed member, an object array, a header that does not describe exactly the
    member's bytes -- is read through ``np.load`` (its errors, ``allow_pickle=False``).
    ``mmap``: stored members as read-only memory maps instead (pages read where used; each
    map holds a file descriptor while it lives, so a caller drops them promptly)."""
    fmt = np.lib.format
    out: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(path) as z, open(path, "rb") as f:
            for info in z.infolist():
                if info.compress_type != zipfile.ZIP_STORED or not info.filename.endswith(".npy"):
                    raise ValueError("not a stored .npy member")
                f.seek(info.header_offset)
                head = f.read(30)
                if len(head) != 30 or head[:4] != b"PK\x03\x04":
                    raise ValueError("no local file header")
                name_len, extra_len = struct.unpack("<2H", head[26:30])
                start = info.header_offset + 30 + name_len + extra_len
                f.seek(start)
                version = fmt.read_magic(f)
                read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
                shape, fortran, dtype = read(f)
                offset = f.tell()
                count = int(np.prod(shape, dtype=np.int64))
                if dtype.hasobject or offset - start + count * dtype.itemsize != info.file_size:
                    raise ValueError("header and member size differ")
                key = info.filename[:-4]
                order = "F" if fortran else "C"
                if mmap and count:
                    # a plain ndarray view (compiled kernels take it), the map its base
                    out[key] = np.asarray(np.memmap(path, dtype=dtype, mode="r", offset=offset,
                                                    shape=shape, order=order))
                    continue
                # one read into the array (no zip stream, no CRC pass; no file kept open)
                a = np.fromfile(f, dtype=dtype, count=count)
                if len(a) != count:
                    raise ValueError("member shorter than its header")
                out[key] = a.reshape(shape, order=order)
    except (ValueError, OSError, zipfile.BadZipFile, struct.error):
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    return out


@contextmanager
def atomic_directory(path: str | Path, *, overwrite: bool = False):
    """Build a directory under a temporary sibling name; rename it into place on success.

    On any exception the temporary directory is removed and ``path`` is left as it was.
    With ``overwrite`` an existing ``path`` is replaced only after the new one is complete.
    """
    path = Path(path).absolute()
    if path.exists() and not overwrite:
        raise FileExistsError(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_partials(path)
    # the owner's pid is in the name, so that a later run can tell a killed run's leftovers
    # (SIGKILL, an out-of-memory kill, a power cut) from a live one's work in progress
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.{os.getpid()}-", suffix=".partial",
                                dir=path.parent))
    os.chmod(tmp, ordinary_mode(directory=True))
    try:
        yield tmp
        for root, _dirs, files in os.walk(tmp):
            for name in files:
                fd = os.open(os.path.join(root, name), os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
        if path.exists():
            old = path.with_name(f".{path.name}.old-{os.getpid()}")
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
        fsync_dir(path.parent)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this host (someone else's live process counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def remove_stale_partials(path: str | Path) -> list[Path]:
    """Remove what killed runs of :func:`atomic_directory` left beside ``path``.

    ``.NAME.<pid>-XXXX.partial`` (a folder being built) and ``.NAME.old-<pid>`` (the previous
    version during the swap) whose process no longer runs. A live process's folders stay.
    Returns the folders removed."""
    path = Path(path).absolute()
    removed = []
    if not path.parent.is_dir():
        return removed
    pat = re.compile(rf"^\.{re.escape(path.name)}\.(?:(\d+)-.*\.partial|old-(\d+))$")
    for p in path.parent.iterdir():
        m = pat.match(p.name)
        if not m or not p.is_dir() or p.is_symlink():
            continue
        pid = int(m.group(1) or m.group(2))
        if pid != os.getpid() and not pid_alive(pid):
            shutil.rmtree(p, ignore_errors=True)
            removed.append(p)
    return removed


def own_rss() -> int:
    """This process's resident memory in bytes (Linux; 0 where unknown)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return 0
    return 0


def require_memory(need: int, what: str, *, detail: str = "", hint: str = "",
                   error: type[Exception] | None = None, count_own: bool = False) -> dict:
    """Refuse up front when a step's memory estimate does not fit.

    ``need`` bytes are compared with the memory available now (Linux ``MemAvailable``, plus
    this process's own resident memory with ``count_own``; not checked where it is unknown).
    When it does not fit, ``error`` (default :class:`~occufly.errors.OccuflyError`: CLI exit 2,
    HTTP 4xx) is raised before any work with "WHAT needs about N GB of memoryDETAIL, M GB are
    available; HINT". Returns ``{"memory_bytes", "available_bytes"}`` for the step's report."""
    avail = available_memory()
    if avail is not None and count_own:
        avail += own_rss()
    if avail is not None and need > avail:
        if error is None:
            from occufly.errors import OccuflyError as error
        gb = 2.0 ** 30
        raise error(f"{what} needs about {need / gb:.1f} GB of memory{detail}, {avail / gb:.1f} GB "
                    f"are available" + (f"; {hint}" if hint else ""))
    return {"memory_bytes": need, "available_bytes": avail}


def available_memory() -> int | None:
    """MemAvailable in bytes (Linux), else None (not checked)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


class PathNotConfined(ValueError):
    """A path read from a file resolves (symlinks followed) outside every allowed root."""


def confined(path: str | Path, roots) -> Path:  # noqa: ANN001
    """``path`` resolved with ``os.path.realpath`` (symlinks followed) if it lies inside one of
    ``roots`` (each resolved the same way); raises PathNotConfined naming the path otherwise.

    The one confinement check for paths that come from files (scene.json image paths,
    reconstruction photo paths): used at import and again when an image is served. A path
    with a NUL byte (no file has one) is refused the same way, never a ValueError."""
    if "\x00" in os.fspath(path):
        raise PathNotConfined(f"{str(path)!r} contains a NUL byte")
    real = Path(os.path.realpath(path))
    for root in roots:
        r = Path(os.path.realpath(root))
        if real == r or r in real.parents:
            return real
    raise PathNotConfined(f"{path} resolves to {real}, outside the import roots and the data dir")


IMAGE_MAGIC = ((b"\x89PNG\r\n\x1a\n", "image/png"), (b"\xff\xd8\xff", "image/jpeg"),
               (b"II*\x00", "image/tiff"), (b"MM\x00*", "image/tiff"))


def image_content_type(path: str | Path) -> str | None:
    """The image media type decided from the file's first bytes (never from its name), or None."""
    with open(path, "rb") as fh:
        head = fh.read(16)
    for magic, kind in IMAGE_MAGIC:
        if head.startswith(magic):
            return kind
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return "image/webp"
    return None
