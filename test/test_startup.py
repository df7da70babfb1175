"""Start-up: numba cache location (read-only installs), one compiled specialisation per kernel, no
heavy imports on the node paths. Timing itself is measured by ``python -m
benchmarks.bench_startup``, not here.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

import afm_ros
from afm_ros import numba_cache

PACKAGE = Path(afm_ros.__file__).resolve().parent


# --- choice of the cache directory (in process) -----------------------------------------------
@pytest.fixture
def clean_cache_state(monkeypatch):
    """configure() may set NUMBA_CACHE_DIR and numba's config: restore both after the test (else
    every later compile and every later child process of the suite uses a deleted temporary cache:
    cold)."""
    monkeypatch.setenv(
        "NUMBA_CACHE_DIR", ""
    )  # records the original state (delenv of an unset name would not)
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setattr(numba_cache, "chosen", numba_cache.chosen)
    monkeypatch.setattr(numba_cache, "reason", numba_cache.reason)
    config = sys.modules.get("numba.core.config")
    before = config.CACHE_DIR if config is not None else os.environ.get("NUMBA_CACHE_DIR", "")
    yield monkeypatch
    config = sys.modules.get("numba.core.config")  # the test may have imported numba
    if config is not None:
        config.CACHE_DIR = before


def test_user_set_numba_cache_dir_wins(clean_cache_state, tmp_path):
    clean_cache_state.setenv("NUMBA_CACHE_DIR", str(tmp_path / "mine"))
    clean_cache_state.setattr(numba_cache, "_in_tree_writable", lambda: False)
    assert numba_cache.configure() == str(tmp_path / "mine")
    assert os.environ["NUMBA_CACHE_DIR"] == str(tmp_path / "mine")
    assert numba_cache.chosen is None


def test_read_only_package_falls_back_to_xdg_cache_home(clean_cache_state, tmp_path):
    clean_cache_state.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    clean_cache_state.setattr(numba_cache, "_in_tree_writable", lambda: False)
    expected = str(tmp_path / "xdg" / "afm_ros" / "numba")
    assert numba_cache.configure() == expected
    assert os.environ["NUMBA_CACHE_DIR"] == expected and Path(expected).is_dir()
    import numba.core.config

    assert numba.core.config.CACHE_DIR == expected  # numba already imported here: told directly


def test_without_xdg_cache_home_uses_home_cache(clean_cache_state, tmp_path):
    clean_cache_state.delenv("XDG_CACHE_HOME", raising=False)
    clean_cache_state.setenv("HOME", str(tmp_path))
    clean_cache_state.setattr(numba_cache, "_in_tree_writable", lambda: False)
    assert numba_cache.configure() == str(tmp_path / ".cache" / "afm_ros" / "numba")


def test_writable_package_keeps_numbas_in_tree_cache(clean_cache_state):
    if not numba_cache._in_tree_writable():
        pytest.skip("this checkout is not writable")
    assert numba_cache.configure() is None
    assert "NUMBA_CACHE_DIR" not in os.environ


# --- read-only install, run as a user who cannot write it (subprocess) ------------------------
CHILD = r"""
import json, os, sys
import afm_ros
from afm_ros import numba_cache
before_numba = "numba" not in sys.modules
from afm_ros.core.physics import events, simulation
from afm_ros.core import lockin
simulation.Simulation().advance(100, 4)  # the default integrator: rk4_event
lockin.LockIn().warm_up()
print(json.dumps({
    "package": afm_ros.__file__, "chosen": numba_cache.chosen, "reason": numba_cache.reason,
    "env": os.environ.get("NUMBA_CACHE_DIR"), "configured_before_numba": before_numba,
    "hits": sum(sum(d.stats.cache_hits.values())
                for d in (events.advance_event, lockin._demodulate)),
    "misses": sum(sum(d.stats.cache_misses.values())
                  for d in (events.advance_event, lockin._demodulate)),
}))
"""

PROBE = r"""
import os, sys
# the user must be able to read the environment (a checkout under a 0700 dir is not)
import numpy, numba
ro, home = sys.argv[1], sys.argv[2]
try:
    open(os.path.join(ro, "probe"), "w").close()
    sys.exit("install writable")
except PermissionError:
    pass
open(os.path.join(home, "probe"), "w").close()
os.remove(os.path.join(home, "probe"))
"""


def _mechanisms():
    """Ways to run a process that is subject to file permissions (root is not)."""
    out = []
    if os.geteuid() != 0:
        out.append(("current user", []))
        return out
    setpriv, runuser = shutil.which("setpriv"), shutil.which("runuser")
    if setpriv:
        out.append(
            (
                "nobody via setpriv",
                [setpriv, "--reuid=nobody", "--regid=nogroup", "--clear-groups"],
            )
        )
    if runuser:
        out.append(("nobody via runuser", [runuser, "-u", "nobody", "--"]))
    if setpriv:  # uid 0 without any capability: permission bits apply, the owner's included
        out.append(
            ("root without capabilities", [setpriv, "--bounding-set=-all", "--inh-caps=-all"])
        )
    return out


@pytest.fixture
def read_only_install():
    """A copy of the package in a directory nobody may write (dirs 0555, files 0444) and a HOME
    the test process's unprivileged child may write; the mechanism that works here, or skip."""
    base = Path(tempfile.mkdtemp(prefix="afm_ro_"))
    try:
        base.chmod(0o755)
        install = base / "install"
        shutil.copytree(
            PACKAGE, install / "afm_ros", ignore=shutil.ignore_patterns("__pycache__", "*.pyc")
        )
        home = base / "home"
        home.mkdir()
        home.chmod(0o777)
        for root, dirs, files in os.walk(install):
            for f in files:
                os.chmod(os.path.join(root, f), 0o444)
        for root, dirs, files in os.walk(install, topdown=False):
            os.chmod(root, 0o555)
        env = {
            k: v
            for k, v in os.environ.items()
            if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME", "PYTHONPATH")
        }
        env.update(HOME=str(home), PYTHONPATH=str(install), PYTHONDONTWRITEBYTECODE="1")
        reasons = []
        for name, prefix in _mechanisms():
            probe = subprocess.run(
                prefix + [sys.executable, "-c", PROBE, str(install / "afm_ros"), str(home)],
                env=env,
                cwd=str(home),
                capture_output=True,
                text=True,
                timeout=60,
            )
            if probe.returncode == 0:
                yield name, prefix, install, home, env
                break
            reasons.append(
                f"{name}: "
                f"{(probe.stderr.strip().splitlines() or ['exit %d' % probe.returncode])[-1]}"
            )
        else:
            pytest.skip(
                "cannot run a process that is denied writing the install: " + "; ".join(reasons)
            )
    finally:
        for root, dirs, files in os.walk(base):
            os.chmod(root, stat.S_IRWXU)
        shutil.rmtree(base, ignore_errors=True)


@pytest.mark.slow
def test_read_only_install_caches_in_the_user_dir_and_starts_warm(read_only_install):
    name, prefix, install, home, env = read_only_install
    print(f"unprivileged process: {name}")

    def start():
        run = subprocess.run(
            prefix + [sys.executable, "-c", CHILD],
            env=env,
            cwd=str(home),
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert run.returncode == 0, f"{name}: {run.stderr[-2000:]}"
        return json.loads(run.stdout.strip().splitlines()[-1])

    user_dir = home / ".cache" / "afm_ros" / "numba"
    first = start()
    assert first["package"].startswith(str(install)), first
    assert first["configured_before_numba"]
    assert first["chosen"] == str(user_dir) == first["env"], first
    assert first["misses"] >= 2 and first["hits"] == 0, first  # compiled: nothing was cached yet
    cached = sorted(p.name for p in user_dir.rglob("*") if p.is_file())
    assert any(n.startswith("events.advance_event") and n.endswith(".nbc") for n in cached), cached
    assert any(n.startswith("lockin._demodulate") and n.endswith(".nbc") for n in cached), cached
    assert not list(install.rglob("__pycache__")), "nothing may be written into the install"

    second = start()
    assert second["chosen"] == str(user_dir)
    assert second["hits"] >= 2 and second["misses"] == 0, second  # warm: loaded, not compiled


# --- compiled specialisations and imports ------------------------------------------------------
def test_rk4_kernel_has_one_specialisation_for_any_argument_types():
    from afm_ros.core.physics import events, integrators, seed_simulation

    for method, kernel in (("rk4", integrators._advance), ("rk4_event", events.advance_event)):
        sim = seed_simulation(z_base=40e-9, method=method)
        sim.advance(10)
        sim.z_offset = 0  # an int, as a caller might pass
        sim.advance(10, np.int64(2))
        sim.z_offset = np.float64(40e-9)
        sim.advance(np.int64(10))
        assert len(kernel.signatures) == 1, (method, kernel.signatures)


def test_lockin_filter_stage_is_inlined_not_compiled_per_column():
    from afm_ros.core import lockin

    lockin.LockIn().warm_up()
    assert len(lockin._demodulate.signatures) == 1
    assert lockin._cascade.signatures == []  # inlined into _demodulate: no own compilation


@pytest.mark.parametrize(
    "module,forbidden",
    [
        (
            "afm_ros.nodes.cantilever_node",
            ("matplotlib", "tqdm", "scipy.integrate", "afm_ros.core.physics.analysis"),
        ),
        (
            "afm_ros.nodes.lockin_node",
            ("matplotlib", "tqdm", "scipy.integrate", "scipy.signal", "scipy.special"),
        ),
        ("afm_ros.nodes.z_controller_node", ("matplotlib", "tqdm", "numba", "scipy")),
    ],
)
def test_node_imports_stay_light(module, forbidden):
    code = f"import sys, {module}; print([m for m in {list(forbidden)!r} if m in sys.modules])"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.strip() == "[]", f"{module} imports {run.stdout.strip()}"


def test_every_folder_with_numba_kernels_is_checked_for_the_in_tree_cache():
    """numba_cache decides between the in-tree cache and a user cache by the folders that hold
    kernels (cache=True writes beside their sources): a folder missing there would send every
    start to the fallback cache (it happened when the package was split into subpackages)."""
    import pathlib

    package = pathlib.Path(numba_cache.PACKAGE_DIR)
    with_kernels = {str(p.parent) for p in package.rglob("*.py") if "njit(" in p.read_text()}
    assert with_kernels <= set(map(os.path.normpath, numba_cache.KERNEL_DIRS)), sorted(
        with_kernels
    )


def test_cached_kernels_are_dropped_when_any_kernel_source_changes(tmp_path):
    """numba checks a cached kernel against its own file only; the scanning kernel inlines the
    event kernel of another file. The stamp of every kernel source decides: unchanged sources keep
    the cache, a changed one (any file) drops it."""
    from afm_ros import numba_cache

    cached = tmp_path / "integrators.advance_surface-184.py311.nbi"
    cached.write_text("x")
    assert numba_cache.drop_stale(
        str(tmp_path), [str(cached)]
    )  # no stamp yet: dropped, stamp written
    cached.write_text("x")
    assert not numba_cache.drop_stale(str(tmp_path), [str(cached)]) and cached.exists()
    (tmp_path / "afm_ros_sources.stamp").write_text("an older set of sources\n")
    assert numba_cache.drop_stale(str(tmp_path), [str(cached)]) and not cached.exists()
