"""Compiled parts of the optimizer and its validation: built once against the installed Crocoddyl
and MuJoCo, loaded if they build.

One module (`module.cpp`) with two Crocoddyl C++ classes and two functions (and `cpu_has_avx2_fma`):
- `MatchedEulerModel` (`matched_euler.hpp`), the matched integrator (`trajopt.integrator`) as an
  action model: the same step and derivatives, without Python in a node's `calc` and `calcDiff`
  (30 % and about 20 % of their time), and with datas that Crocoddyl's problems accept (the
  receding windows then reuse each node's data instead of allocating one per window);
- `BarrierCostModel` (`barrier_cost.hpp`), Crocoddyl's residual cost with its derivatives skipped
  where the activation is flat: a barrier inside its bounds (a wrench inside its cone, joints inside
  their limits) costs no residual derivatives and no products of zeros, and one with a few active rows
  multiplies those rows alone (`trajopt.costs`);
- `feedback_replay` (`feedback_replay.hpp`), the validation's 1-kHz replay under the optimizer's
  feedback law (`data.replay.Replayer.feedback_states`) as one loop around MuJoCo's `mj_step`,
  reaching the model and data through the Python objects' addresses: the Python loop spent about as
  long around the physics as in it;
- `track_frames` (`frame_tracking.hpp`), the 200 Hz frames' tracking law over one coarse node
  (`trajopt.tracking.NodeTracking`, run by `frames.complete`): two evaluations of the node's 5-ms
  model per frame, which the Python loop spent about three times as long around, and the law's gain
  at the node's first frame (Fu from the KKT inverse, without the node's other derivatives); frames whose
  wrenches leave their cones come back to Python for their projection.

It is compiled on first use with the C++ compiler of the machine (`$CXX`, else `c++`) against the
headers that the pinned wheels ship (crocoddyl, pinocchio, boost, mujoco; Eigen from `cmeel-eigen`), into
`<cache>/native/<key>/` (the temporary folder's `opt2skill-<uid>/` where the cache is not
writable), where the key hashes the sources, the compiled stack's versions and the Python ABI.
`make install` builds it, so tests and workers find it ready. Processes that race to build it take
a file lock; the module appears by atomic rename.

Where it cannot be built (no compiler, no Python headers) or `OPT2SKILL_NATIVE=0` is set, `load()`
returns None and says why once in the log; the callers then use the Python integrator,
Crocoddyl's own residual costs and the Python replay and frame loops, whose results agree to round-off
(tests/test_trajopt_native.py, tests/test_data_validate.py).
`python -m opt2skill.trajopt.native` builds it and prints where, or why not (exit status 1).

A second module (`simd_module.cpp`, loaded by `load_simd()`) holds what pays to compile for AVX2 and
FMA, which the wheels are built without: `BoxFDDP` (`riccati.hpp`), Crocoddyl's Box-FDDP with its
backward pass's products compiled here (a quarter of a walk's solve; about a third faster), and
`ContactFwdDynamics` (`contact_dynamics.hpp`), Crocoddyl's contact forward dynamics with the matrix
products of its derivatives and the sum of its costs' derivatives (`cost_sum.hpp`, over the blocks each
cost fills) compiled here (`trajopt.phases.contact_dynamics`). It is
built and loaded only where the CPU has both (`cpu_has_avx2_fma` of the first module), with Eigen's
alignment and allocation kept at the wheels'; elsewhere, or where it does not build, the optimizer
uses Crocoddyl's classes, whose plans these give to round-off (tests/test_trajopt_native.py).
"""

from __future__ import annotations

import fcntl
import hashlib
import importlib.util
import logging
import os
import shlex
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from types import ModuleType

log = logging.getLogger(__name__)

MODULE = "_native"
SOURCE = Path(__file__).with_name("module.cpp")
SIMD_HEADERS = tuple(Path(__file__).with_name(name)
                     for name in ("contact_dynamics.hpp", "cost_sum.hpp", "dynamics_terms.hpp", "riccati.hpp"))
HEADERS = tuple(sorted(set(Path(__file__).parent.glob("*.hpp")) - set(SIMD_HEADERS)))  # included by SOURCE
STACK = ("crocoddyl", "pin", "libpinocchio", "cmeel-boost", "cmeel-eigen", "mujoco")  # what the binary depends on

# What Pinocchio's CMake config gives its users (INTERFACE_COMPILE_DEFINITIONS): its joint variant
# has more alternatives than Boost.MPL's preprocessed lists hold.
PINOCCHIO_DEFINITIONS = ("-DBOOST_MPL_LIMIT_LIST_SIZE=30", "-DBOOST_MPL_LIMIT_VECTOR_SIZE=30",
                         "-DBOOST_MPL_CFG_NO_PREPROCESSED_HEADERS", "-DBOOST_FUSION_INVOKE_MAX_ARITY=12")

# The second module: Eigen vectorizes with AVX2 and FMA, but keeps what the wheels' objects were laid
# out and allocated with: 16-byte alignment, static and dynamic, and glibc's malloc and free for the
# heap (with AVX Eigen would otherwise over-allocate and offset its blocks, and a matrix resized here
# would be freed wrongly by the wheels: the first build crashed so). Its symbols stay inside it, so
# neither module's copies of Eigen's kernels stand in for the other's.
SIMD_MODULE = "_native_simd"
SIMD_SOURCE = Path(__file__).with_name("simd_module.cpp")
SIMD_FLAGS = ("-mavx2", "-mfma", "-DEIGEN_MAX_ALIGN_BYTES=16", "-DEIGEN_MAX_STATIC_ALIGN_BYTES=16",
              "-DEIGEN_MALLOC_ALREADY_ALIGNED=1",
              "-fvisibility=hidden", "-fvisibility-inlines-hidden", "-Wl,-Bsymbolic")

_loaded: ModuleType | None = None
_reason: str | None = None  # why it is not loaded, once tried
_simd: ModuleType | None = None
_simd_reason: str | None = None


@dataclass(frozen=True)
class _Extension:
    module: str
    source: Path
    headers: tuple[Path, ...]  # what the source includes: part of the build's key
    flags: tuple[str, ...] = ()


def _main_extension() -> _Extension:
    return _Extension(MODULE, SOURCE, HEADERS)  # read when called: tests point SOURCE elsewhere


def _simd_extension() -> _Extension:
    return _Extension(SIMD_MODULE, SIMD_SOURCE, SIMD_HEADERS, SIMD_FLAGS)


class NativeBuildError(RuntimeError):
    """The extension could not be compiled here; the message says what was missing or what failed."""


def cache_root() -> Path:
    """`$OPT2SKILL_CACHE`, else `$XDG_CACHE_HOME/opt2skill`, else `~/.cache/opt2skill`."""
    if os.environ.get("OPT2SKILL_CACHE"):
        return Path(os.environ["OPT2SKILL_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "opt2skill"


def _versions() -> dict[str, str]:
    out = {}
    for name in STACK:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "missing"
    return out


def build_key(extension: _Extension | None = None) -> str:
    """Changes whenever a source, the flags, the compiled stack or the Python ABI does."""
    extension = extension or _main_extension()
    h = hashlib.sha256(extension.source.read_bytes())
    for header in extension.headers:
        h.update(header.read_bytes())
    h.update(repr(extension.flags).encode())
    h.update(repr(sorted(_versions().items())).encode())
    h.update((sys.implementation.cache_tag + sysconfig.get_config_var("EXT_SUFFIX")).encode())
    return h.hexdigest()[:16]


def stack_prefix() -> Path:
    """The folder the compiled stack's wheels install into (include/, lib/)."""
    import crocoddyl

    for parent in Path(crocoddyl.__file__).resolve().parents:
        if (parent / "include" / "crocoddyl").is_dir() and (parent / "lib").is_dir():
            return parent
    raise NativeBuildError(f"no include/crocoddyl above {crocoddyl.__file__}: the crocoddyl wheel ships no headers")


def mujoco_folder() -> tuple[Path, Path]:
    """The mujoco wheel's headers folder and its shared library (the wheel ships both)."""
    import mujoco

    folder = Path(mujoco.__file__).resolve().parent
    libraries = sorted(folder.glob("libmujoco.so*"))
    if not (folder / "include" / "mujoco" / "mujoco.h").exists() or not libraries:
        raise NativeBuildError(f"the mujoco wheel at {folder} ships no include/mujoco/mujoco.h or libmujoco.so")
    return folder / "include", libraries[-1]


def compiler() -> list[str]:
    return shlex.split(os.environ.get("CXX", "c++"))


def missing_prerequisite() -> str | None:
    """What this machine lacks for the build (the first thing found), or None."""
    if shutil.which(compiler()[0]) is None:
        return f"no C++ compiler: {compiler()[0]!r} not found (set CXX)"
    try:
        prefix = stack_prefix()
    except NativeBuildError as exc:
        return str(exc)
    try:
        mujoco_folder()
    except NativeBuildError as exc:
        return str(exc)
    include = prefix / "include"
    for need, what in ((Path(sysconfig.get_paths()["include"]) / "Python.h", "Python headers (python3-dev)"),
                       (include / "eigen3" / "Eigen" / "Core", "Eigen headers (pip install cmeel-eigen)"),
                       (include / "boost" / "python.hpp", "boost.python headers (cmeel-boost)")):
        if not need.exists():
            return f"{what} not found: {need}"
    return None


def compile_command(prefix: Path, target: Path, extension: _Extension | None = None) -> list[str]:
    extension = extension or _main_extension()
    include = prefix / "include"
    boost_python = f"boost_python{sys.version_info.major}{sys.version_info.minor}"
    mujoco_include, libmujoco = mujoco_folder()
    return [
        *compiler(), "-O2", "-std=c++17", "-shared", "-fPIC", "-DNDEBUG", "-w", *PINOCCHIO_DEFINITIONS,
        # Crocoddyl's multibody headers include Pinocchio 3's paths, which Pinocchio 4 keeps under deprecated/.
        f"-I{include}", f"-I{include / 'pinocchio' / 'deprecated'}", f"-I{include / 'eigen3'}", f"-I{mujoco_include}", f"-I{sysconfig.get_paths()['include']}",
        *extension.flags, str(extension.source), "-o", str(target),
        f"-L{prefix / 'lib'}", "-lcrocoddyl", "-lpinocchio_default", f"-l{boost_python}",
        f"-L{libmujoco.parent}", f"-l:{libmujoco.name}",
        f"-Wl,-rpath,{prefix / 'lib'}", f"-Wl,-rpath,{libmujoco.parent}",
    ]


def build_folder(extension: _Extension | None = None) -> Path:
    """This build's folder in the cache, created; in the temporary folder if the cache is not writable."""
    fallback = Path(tempfile.gettempdir()) / f"opt2skill-{os.getuid()}"
    for root in (cache_root(), fallback):
        folder = root / "native" / build_key(extension)
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(folder, os.W_OK):
            return folder
    raise NativeBuildError(f"no writable folder for the build: {cache_root()} nor {fallback}")


def build(force: bool = False, extension: _Extension | None = None) -> Path:
    """The compiled module's path, compiling it first unless a build for this key exists (or `force`)."""
    extension = extension or _main_extension()
    folder = build_folder(extension)
    target = folder / (extension.module + sysconfig.get_config_var("EXT_SUFFIX"))
    if target.exists() and not force:
        return target
    with open(folder / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another process may be building it right now
        if target.exists() and not force:
            return target
        missing = missing_prerequisite()
        if missing:
            raise NativeBuildError(missing)
        partial = folder / f".{extension.module}.{os.getpid()}.so"
        command = compile_command(stack_prefix(), partial, extension)
        result = subprocess.run(command, capture_output=True, text=True, timeout=600)
        if result.returncode != 0:
            partial.unlink(missing_ok=True)
            tail = (result.stderr or result.stdout).strip().splitlines()[-5:]
            raise NativeBuildError(f"compiling {extension.source.name} failed ({command[0]}): " + " | ".join(tail))
        os.replace(partial, target)
    return target


def _import(path: Path, name: str = MODULE) -> ModuleType:
    import crocoddyl  # noqa: F401  loads the stack's shared libraries, which the module links against

    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def load() -> ModuleType | None:
    """The compiled module, or None (the reason in `unavailable_reason()`, logged once)."""
    global _loaded, _reason
    if _loaded is not None or _reason is not None:
        return _loaded
    if os.environ.get("OPT2SKILL_NATIVE", "1") == "0":
        _reason = "disabled by OPT2SKILL_NATIVE=0"
        return None
    try:
        _loaded, _ = _built_and_imported()
    except (NativeBuildError, ImportError, OSError) as exc:
        _reason = str(exc)
        log.warning("compiled optimizer parts unavailable (%s); using the Python matched integrator and "
                    "Crocoddyl's residual costs, about 20 %% slower", _reason)
    return _loaded


def _built_and_imported(extension: _Extension | None = None) -> tuple[ModuleType, Path]:
    extension = extension or _main_extension()
    path = build(extension=extension)
    try:
        return _import(path, extension.module), path
    except ImportError:  # a damaged build in the cache (a killed copy, a full disk): built again, once
        path = build(force=True, extension=extension)
        return _import(path, extension.module), path


def load_simd() -> ModuleType | None:
    """The module compiled for AVX2 and FMA, or None (the reason in `simd_unavailable_reason()`): where
    the first module is unavailable, the CPU lacks either, or it does not build (logged once)."""
    global _simd, _simd_reason
    if _simd is not None or _simd_reason is not None:
        return _simd
    first = load()
    if first is None:
        _simd_reason = f"the compiled parts are unavailable ({_reason})"
    elif not first.cpu_has_avx2_fma():
        _simd_reason = "this CPU lacks AVX2 or FMA"
    else:
        try:
            _simd, _ = _built_and_imported(_simd_extension())
        except (NativeBuildError, ImportError, OSError) as exc:
            _simd_reason = str(exc)
            log.warning("the solver's parts compiled for AVX2/FMA are unavailable (%s); using Crocoddyl's, "
                        "about 10 %% slower", _simd_reason)
    return _simd


def simd_unavailable_reason() -> str | None:
    load_simd()
    return _simd_reason


def unavailable_reason() -> str | None:
    load()
    return _reason


def main() -> int:
    try:
        _, path = _built_and_imported()
    except (NativeBuildError, ImportError, OSError) as exc:
        print(f"opt2skill: the compiled optimizer parts were not built: {exc}", file=sys.stderr)
        return 1
    print(f"opt2skill: compiled optimizer parts ready: {path}")
    if load_simd() is None:
        print(f"opt2skill: the solver's parts compiled for AVX2/FMA are not used: {simd_unavailable_reason()}")
    else:
        print(f"opt2skill: the solver's parts compiled for AVX2/FMA ready: {build(extension=_simd_extension())}")
    return 0
