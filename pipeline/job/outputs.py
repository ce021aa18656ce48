"""Where a job's files go, and how they get there without ever destroying anything.

The rules (issue 11; SPEC "Files are written atomically"):

- A job name is one plain file name (:func:`job_name_problem`); the job folder is
  ``<out>/<name>`` and is checked to lie directly inside the resolved ``--out`` before anything
  is written, renamed or removed (:func:`job_dir`).
- One writer per job folder: a lock file ``<out>/.<name>.lock`` (``flock``) is held for the
  whole job; a second run of the same job is refused with the holder's pid (:class:`JobLock`).
- Outputs are staged in ``<out>/.<name>.partial``, every file is verified (it is complete: the
  .vdb opens and holds the grids written, XML files are closed, PNGs end with IEND, JSON parses)
  and flushed to disk (``fsync``), and only then is the staging folder swapped with the job folder
  (one atomic ``renameat2(RENAME_EXCHANGE)`` where the kernel has it; else two renames that the
  next run completes if it is interrupted between them). A failure leaves the previous outputs
  untouched and writes ``manifest.failed.json`` beside them.

Hidden names (``.<name>.partial``, ``.<name>.old``, ``.<name>.lock``) cannot clash with a job
folder, because job names never start with a dot.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import json
import os
import shutil
import tempfile
import unicodedata
from collections.abc import Iterable
from pathlib import Path

from pipeline.io.vdbio import read_grids
from pipeline.util.atomic import write_json
from pipeline.util.errors import ConfigError

MAX_NAME_BYTES = 200  # file names are limited to 255 bytes; ".<name>.partial" must fit too
FAILED_MANIFEST = "manifest.failed.json"
_FORBIDDEN = set('/\\:*?"<>|')  # separators, and what Windows/SMB shares refuse in a file name


def job_name_problem(name: str) -> str | None:
    """Why ``name`` cannot be a job name (a folder directly inside ``--out``), or None."""
    if not isinstance(name, str) or not name:
        return "a job name must not be empty"
    if set(name) <= {"."}:
        return f"{name!r} is not a job name: it must be a plain file name, not '.' or '..'"
    if name.startswith("."):
        return f"job name {name!r} must not start with '.' (hidden names are frepvdb's staging folders)"
    bad = sorted({c for c in name if c in _FORBIDDEN or unicodedata.category(c)[0] in "CZ" and c != " "})
    if bad:
        shown = ", ".join(repr(c) for c in bad[:5])
        return f"job name {_short(name)} must be one plain file name: it contains {shown}"
    if name != name.strip():
        return f"job name {name!r} must not start or end with a space"
    size = len(name.encode("utf-8", "surrogatepass"))
    if size > MAX_NAME_BYTES:
        return f"job name {_short(name)} is {size} bytes long; at most {MAX_NAME_BYTES}"
    return None


def _short(name: str, n: int = 40) -> str:
    return repr(name if len(name) <= n else name[:n] + "...")


class OutputError(ConfigError):
    """A bad ``--out`` or an unsafe job folder (exit 2, one line)."""

    def __init__(self, where: str, message: str):
        super().__init__([(where, None, (), message)])


def prepare_out_root(out: str | os.PathLike) -> Path:
    """``--out`` resolved and proven writable (it is created if missing); OutputError if not."""
    raw = os.fspath(out)
    where = f"--out {raw!r}" if raw.strip() != raw or not raw else f"--out {raw}"
    if not raw.strip():
        raise OutputError(where, "must name a folder (it is empty)")
    path = Path(raw).expanduser()
    try:
        if path.exists() and not path.is_dir():
            raise OutputError(where, "is not a folder")
        path.mkdir(parents=True, exist_ok=True)
        probe = tempfile.mkdtemp(prefix=".frepvdb-probe-", dir=path)
        os.rmdir(probe)
    except OSError as e:
        raise OutputError(where, f"cannot write there ({e.strerror or e})") from None
    return path.resolve()


def job_dir(out_root: Path, name: str) -> Path:
    """``<out>/<name>``, checked to be a direct child of the resolved ``out_root``."""
    problem = job_name_problem(name)
    if problem:
        raise OutputError(str(out_root), problem)
    root = Path(out_root).resolve()
    folder = root / name
    if folder.parent != root or folder.name != name:
        raise OutputError(str(root), f"job folder for {name!r} would not lie inside --out")
    if folder.is_symlink():
        raise OutputError(str(folder), "is a symbolic link; frepvdb replaces job folders and does not follow links")
    if folder.exists() and not folder.is_dir():
        raise OutputError(str(folder), "exists and is not a folder; move it away or use another --out")
    return folder


# --- one writer per job ------------------------------------------------------------------------


class JobBusy(RuntimeError):
    """Another run holds the job's lock."""


class JobLock:
    """``flock`` on ``<out>/.<name>.lock``, removed on release. The inode is checked after locking,
    so a lock file unlinked by a finishing holder is never shared by two later runs."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.path = folder.with_name(f".{folder.name}.lock")
        self.fd: int | None = None

    def __enter__(self) -> JobLock:
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
                os.close(fd)
                raise JobBusy(f"job folder {self.folder} is being written by another run (pid {holder}); "
                              "wait for it to finish or use another --out") from None
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if same:
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
                self.fd = fd
                return self
            os.close(fd)  # the holder removed it between our open and our lock: try again

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            with contextlib.suppress(OSError):
                os.unlink(self.path)
            os.close(self.fd)
            self.fd = None


# --- staging, verification, swap ---------------------------------------------------------------


def staging_dir(folder: Path) -> Path:
    return folder.with_name(f".{folder.name}.partial")


def _old_dir(folder: Path) -> Path:
    return folder.with_name(f".{folder.name}.old")


def recover(folder: Path) -> None:
    """Under the job's lock: finish what an interrupted run left (a swap cut between its two
    renames leaves the old outputs at ``.<name>.old``: put them back) and remove its debris."""
    old = _old_dir(folder)
    if old.is_dir() and not old.is_symlink():
        if not folder.exists():
            os.rename(old, folder)
        else:
            shutil.rmtree(old)
    stage = staging_dir(folder)
    if stage.is_dir() and not stage.is_symlink():
        shutil.rmtree(stage)


def new_staging(folder: Path) -> Path:
    recover(folder)
    stage = staging_dir(folder)
    stage.mkdir()
    return stage


def verify_outputs(stage: Path, outputs: Iterable[dict], grids: dict | None = None, main_vdb: str = "") -> None:
    """Every listed file exists and is complete; raises OSError naming the first that is not.
    ``main_vdb`` (the job's ``<name>.vdb``) must hold ``grids`` with their active voxel counts."""
    for entry in outputs:
        path = stage / entry["path"]
        problem = _file_problem(path, grids or {} if entry["path"] == main_vdb else {})
        if problem:
            raise OSError(errno.EIO, f"{problem} (disk full or file size limit?)", str(path))


def _file_problem(path: Path, grids: dict) -> str | None:
    try:
        size = path.stat().st_size
    except OSError as e:
        return f"missing ({e.strerror})"
    if size == 0:
        return "is empty"
    suffix = path.suffix.lower()
    if suffix == ".vdb":
        return _vdb_problem(path, grids)
    if suffix in (".vti", ".vtp", ".vtu", ".pvd"):
        return None if _tail(path).rstrip().endswith(b"</VTKFile>") else "is not a complete VTK XML file"
    if suffix == ".png":
        return None if _tail(path).endswith(b"IEND\xaeB`\x82") else "is not a complete PNG"
    if suffix == ".html":
        return None if _tail(path).rstrip().lower().endswith(b"</html>") else "is not a complete HTML file"
    if suffix == ".json":
        try:
            json.loads(path.read_bytes())
        except ValueError:
            return "is not complete JSON"
    if suffix == ".ply":
        return _ply_problem(path, size)
    if suffix == ".obj":
        return None if _tail(path).endswith(b"\n") else "is not a complete OBJ file"
    if suffix == ".stl":
        return _stl_problem(path, size)
    if suffix == ".3mf":
        return _3mf_problem(path)
    return None


def _stl_problem(path: Path, size: int) -> str | None:
    """Binary STL: exactly 84 + 50 n bytes for the n triangles its header counts."""
    with open(path, "rb") as f:
        head = f.read(84)
    n = int.from_bytes(head[80:84], "little") if len(head) == 84 else -1
    if n >= 0 and size == 84 + 50 * n:
        return None
    return f"has {size} bytes, a binary STL of {n} triangles needs {84 + 50 * n}"


def _3mf_problem(path: Path) -> str | None:
    """3MF: a complete zip (CRCs checked) holding the model part 3D/3dmodel.model."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            if "3D/3dmodel.model" not in z.namelist():
                return "is not a 3MF file (no 3D/3dmodel.model part)"
            bad = z.testzip()
    except (zipfile.BadZipFile, OSError) as e:
        return f"is not a complete 3MF (zip) file ({str(e)[:80]})"
    return None if bad is None else f"is not a complete 3MF file (part {bad} is damaged)"


def _tail(path: Path, n: int = 64) -> bytes:
    with open(path, "rb") as f:
        f.seek(max(0, path.stat().st_size - n))
        return f.read()


def _vdb_problem(path: Path, grids: dict) -> str | None:
    """The file opens, and holds every in-memory grid with its active voxel count."""

    try:
        read = read_grids(path)
    except Exception as e:  # noqa: BLE001 - OpenVDB raises plain RuntimeErrors/KeyErrors here
        return f"does not open as a .vdb ({str(e)[:120]})"
    for name, g in grids.items():
        if name in read and read[name].activeVoxelCount() != g.activeVoxelCount():
            got, want = read[name].activeVoxelCount(), g.activeVoxelCount()
            return f"grid {name!r} reads back with {got} active voxels, not {want}"
    return None


_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2,
              "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
              "double": 8, "float64": 8}


def _ply_problem(path: Path, size: int) -> str | None:
    """Binary PLY: header, then exactly the bytes its elements need (triangles as 3-lists)."""
    with open(path, "rb") as f:
        head = f.read(4096)
    end = head.find(b"end_header\n")
    if not head.startswith(b"ply") or end < 0:
        return "is not a PLY file"
    lines = head[:end].decode("ascii", "replace").splitlines()
    if not any(line.startswith("format binary") for line in lines):
        return None
    need, count = end + len(b"end_header\n"), 0
    for line in lines:
        w = line.split()
        if w[:1] == ["element"]:
            count = int(w[2])
        elif w[:2] == ["property", "list"]:
            need += count * (_PLY_SIZES[w[2]] + 3 * _PLY_SIZES[w[3]])
        elif w[:1] == ["property"]:
            need += count * _PLY_SIZES[w[1]]
    return None if size == need else f"has {size} bytes, its header needs {need}"


def fsync_tree(folder: Path) -> None:
    """Flush every file and folder under ``folder`` (and it) to the disk."""
    for dirpath, _dirs, files in os.walk(folder):
        for name in files:
            fd = os.open(os.path.join(dirpath, name), os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        fsync_dir(Path(dirpath))


def fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def swap_in(stage: Path, folder: Path) -> None:
    """Make ``stage`` the job folder; the previous outputs are removed only after the swap."""
    if folder.exists() and _exchange(stage, folder):
        shutil.rmtree(stage)  # now holds the previous outputs
    else:
        old = _old_dir(folder)
        if folder.exists():
            os.rename(folder, old)
        os.rename(stage, folder)
        if old.exists():
            shutil.rmtree(old)
    fsync_dir(folder.parent)


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Atomically exchange two paths (Linux renameat2); False where the call is unavailable."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False  # not supported by this kernel or file system: the two-rename path
    raise OSError(err, os.strerror(err), str(b))


def write_failure(folder: Path, manifest: dict) -> None:
    """``manifest.failed.json`` in the job folder, beside (never instead of) earlier outputs."""

    folder.mkdir(exist_ok=True)
    write_json(folder / FAILED_MANIFEST, manifest)


def clear_failure(folder: Path) -> None:
    with contextlib.suppress(FileNotFoundError):
        (folder / FAILED_MANIFEST).unlink()


def os_error_line(e: OSError, stage: Path | None = None, folder: Path | None = None) -> str:
    """One line for a write error, naming the path as the user will know it (the job folder,
    not the staging folder; pipeline.util.atomic already names the final file, not its temporary)."""
    path = str(e.filename) if e.filename else ""
    if stage is not None and folder is not None and path.startswith(str(stage)):
        path = str(folder) + path[len(str(stage)):]
    what = e.strerror or str(e)
    return f"cannot write {path}: {what}" if path else f"write error: {what}"

