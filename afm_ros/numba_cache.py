"""Where numba keeps the compiled kernels of afm_ros (``cache=True``), decided before numba loads.

Numba writes its cache next to the sources (``afm_ros/__pycache__``,
``afm_ros/core/physics/__pycache__``) when it can. In a read-only install (``/opt/ros/...``, a
root-owned site-packages used by another user, a read-only image) it cannot, and every start
would compile the kernels again. :func:`configure` runs from ``afm_ros/__init__.py``, so before
any afm_ros module imports numba, and picks in this order:

1. ``NUMBA_CACHE_DIR`` if the user set it (numba's own variable: it always wins);
2. the package's own directories, if writable (numba's default; nothing is changed);
3. ``$XDG_CACHE_HOME/afm_ros/numba`` (default ``~/.cache/afm_ros/numba``), if it can be created
   and written;
4. ``<tempdir>/afm_ros-numba-<uid>`` as the last resort (without any writable place, numba would
   refuse to define a cached function at all).

In cases 3 and 4 ``NUMBA_CACHE_DIR`` is set in ``os.environ`` (child processes make the same
choice) and, if numba was already imported by someone else, in ``numba.config`` too; numba
then keeps the files of each source directory in its own sub-directory, keyed by the path.

Numba checks a cached kernel against its own source file only, not against the files whose
functions it inlined or calls (the scanning kernel in ``integrators.py`` inlines and calls the
event kernel of ``events.py``): after a ``git pull`` that changed only ``events.py`` it would load
a stale kernel. :func:`configure` therefore keeps a stamp of every kernel source (path, size,
mtime) beside the cache (cases 2-4) and removes the cached kernels when it differs: the next start
compiles them again (tens of seconds once).
"""

from __future__ import annotations

import glob
import hashlib
import os
import sys
import tempfile

PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__))
# the directories that hold modules with cached kernels (their __pycache__ is numba's in-tree
# cache) every folder with numba kernels (cache=True writes beside their sources)
KERNEL_DIRS = (
    PACKAGE_DIR,
    os.path.join(PACKAGE_DIR, "core"),
    os.path.join(PACKAGE_DIR, "core", "physics"),
    os.path.join(PACKAGE_DIR, "core", "samples"),
)

chosen: str | None = None  # the directory set by configure(), None if numba's default is used
reason: str = "not configured"


def _writable_dir(path: str, create: bool) -> bool:
    """True if files can be created in ``path`` (made if ``create``), as numba will need."""
    try:
        if create:
            os.makedirs(path, exist_ok=True)
        if not os.path.isdir(path):
            return False
        # an actual file, not os.access: a read-only mount, ACLs or root without
        # CAP_DAC_OVERRIDE are all caught the same way numba itself would run into them
        with tempfile.TemporaryFile(dir=path):
            pass
        return True
    except OSError:
        return False


def _in_tree_writable() -> bool:
    for d in KERNEL_DIRS:
        pycache = os.path.join(d, "__pycache__")
        # numba creates __pycache__ itself if the package directory allows it
        target = pycache if os.path.isdir(pycache) else d
        if not _writable_dir(target, create=False):
            return False
    return True


def user_cache_dir() -> str:
    """``$XDG_CACHE_HOME/afm_ros/numba``, or ``~/.cache/afm_ros/numba``."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    if not os.path.isabs(base):
        base = os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "afm_ros", "numba")


def sources_stamp() -> str:
    """A digest of the path, size and modification time of every module in KERNEL_DIRS."""
    h = hashlib.sha256()
    for d in KERNEL_DIRS:
        for path in sorted(glob.glob(os.path.join(d, "*.py"))):
            st = os.stat(path)
            h.update(
                f"{os.path.relpath(path, PACKAGE_DIR)}:{st.st_size}:{st.st_mtime_ns};".encode()
            )
    return h.hexdigest()


def drop_stale(stamp_dir: str, cache_files: list[str]) -> bool:
    """Remove ``cache_files`` if the stamp in ``stamp_dir`` is not the sources' (then write it);
    True if they were removed. Errors (a read-only place, a file another process removed) are
    ignored."""
    stamp_file = os.path.join(stamp_dir, "afm_ros_sources.stamp")
    now = sources_stamp()
    try:
        with open(stamp_file) as fh:
            if fh.read().strip() == now:
                return False
    except OSError:
        pass
    for f in cache_files:
        try:
            os.remove(f)
        except OSError:
            pass
    try:
        os.makedirs(stamp_dir, exist_ok=True)
        with open(stamp_file, "w") as fh:
            fh.write(now + "\n")
    except OSError:
        pass
    return True


def _cached(root: str, recursive: bool) -> list[str]:
    pattern = os.path.join(root, "**", "*.nb[ic]") if recursive else os.path.join(root, "*.nb[ic]")
    return glob.glob(pattern, recursive=recursive)


def configure() -> str | None:
    """Choose the cache directory (see the module docstring); return it, or None for in-tree."""
    global chosen, reason
    user_set = os.environ.get("NUMBA_CACHE_DIR", "")
    if user_set:
        chosen, reason = None, "NUMBA_CACHE_DIR set by the user"
        return user_set
    if _in_tree_writable():
        chosen, reason = None, "package directory writable (numba's in-tree cache)"
        drop_stale(
            os.path.join(PACKAGE_DIR, "__pycache__"),
            [f for d in KERNEL_DIRS for f in _cached(os.path.join(d, "__pycache__"), False)],
        )
        return None
    candidates = [
        (user_cache_dir(), "package directory read-only: user cache"),
        (
            os.path.join(
                tempfile.gettempdir(),
                f"afm_ros-numba-{os.getuid() if hasattr(os, 'getuid') else 0}",
            ),
            "package directory and user cache read-only: temporary directory",
        ),
    ]
    for path, why in candidates:
        if _writable_dir(path, create=True):
            chosen, reason = path, why
            drop_stale(path, _cached(path, True))
            os.environ["NUMBA_CACHE_DIR"] = path
            config = sys.modules.get("numba.core.config")
            if config is not None:  # numba was imported before afm_ros: tell it directly as well
                config.CACHE_DIR = path
            return path
    chosen, reason = None, "no writable cache directory found"
    return None


def compilations() -> int:
    """Kernels of afm_ros compiled in this process so far (numba's cache misses of the modules
    loaded): a timing that includes them includes compiling, not only running (a cold cache)."""
    numba = sys.modules.get("numba")
    if numba is None:
        return 0
    from numba.core.dispatcher import Dispatcher  # noqa: PLC0415 - only once numba is loaded

    total = 0
    for name, module in list(sys.modules.items()):
        if not name.startswith("afm_ros.") or module is None:
            continue
        for obj in list(vars(module).values()):
            if isinstance(obj, Dispatcher):
                total += sum(obj.stats.cache_misses.values())
    return total
