"""Real PX4 SITL (the SIH quadrotor, headless) as a child process: find, unpack, start, talk, stop.

The prebuilt SITL in ``../shared/px4-sitl/px4-sitl-sih.tar.gz`` is unpacked once into a cache
folder keyed by the tarball's hash, then :class:`Px4Sitl` starts ``run-sih.sh`` on a free
instance number (no lockstep: PX4's clock is the wall clock, as on a real flight controller),
waits for PX4's "Ready for takeoff!", and gives the MAVLink URLs of its links::

    with Px4Sitl(params={"COM_OF_LOSS_T": 1.0}) as sitl:
        sitl.onboard_url   # the companion's link: PX4 sends from 14580+i to this port
        sitl.gcs_url       # a ground station / MAVSDK: PX4's GCS link sends here
        sitl.uorb_top_hz(["trajectory_setpoint"])   # PX4's own view of its topics

PX4 runs in its own process group; :meth:`Px4Sitl.stop` (also at interpreter exit) ends the
whole group with SIGTERM, then SIGKILL, so no ``px4`` is ever left behind. Its console log
stays in :attr:`Px4Sitl.workdir` when start-up failed or ``keep_workdir`` is set.
"""

from __future__ import annotations

import atexit
import contextlib
import fcntl
import hashlib
import logging
import os
import re
import shutil
import signal
import socket
import subprocess
import tarfile
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType

from companion.errors import SimulationError

log = logging.getLogger(__name__)

#: Environment variable naming the SITL tarball (overrides the default beside the repository).
TARBALL_ENV = "COMPANION_PX4_SITL"
#: The tarball's place in ``shared/`` (which sits beside the repository, or beside a folder
#: above it when the checkout is a git worktree).
SHARED_TARBALL = Path("shared") / "px4-sitl" / "px4-sitl-sih.tar.gz"
_REPO = Path(__file__).resolve().parents[2]
#: The line PX4's commander prints once every pre-flight check passes (EKF, GPS, home).
READY_LINE = "Ready for takeoff!"
#: Instances tried (0 is left to a ground station's default; 14540+i stays below 14550).
INSTANCES = range(1, 10)

#: Per-instance UDP ports ``run-sih.sh`` binds or sends to (PX4's local, then remote ports).
_PORT_BASES = (14580, 14540, 18570, 14280, 14030, 13030, 13280, 19450, 19410)
_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


class Px4SitlError(SimulationError):
    """The SITL could not be found, unpacked, started or talked to; the message says which."""


def tarball_path(explicit: str | Path | None = None) -> Path:
    """The SITL tarball: ``explicit``, else ``$COMPANION_PX4_SITL``, else the nearest
    ``shared/px4-sitl/px4-sitl-sih.tar.gz`` beside the repository or a folder above it (the
    one beside the repository when there is none; see :func:`sitl_available`)."""
    if explicit is not None:
        return Path(explicit)
    env = os.environ.get(TARBALL_ENV)
    if env:
        return Path(env)
    for folder in _REPO.parents:
        if (folder / SHARED_TARBALL).is_file():
            return folder / SHARED_TARBALL
    return _REPO.parent / SHARED_TARBALL


def sitl_available(explicit: str | Path | None = None) -> tuple[bool, str]:
    """``(True, path)`` when the tarball exists, else ``(False, reason)`` (tests skip with it)."""
    path = tarball_path(explicit)
    if path.is_file():
        return True, str(path)
    return False, f"PX4 SITL tarball not found at {path} (set ${TARBALL_ENV} or put it in ../shared/px4-sitl/)"


def cache_root() -> Path:
    """Where unpacked SITLs live: ``$XDG_CACHE_HOME/semantic-companion/px4-sitl`` (default ``~/.cache``)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "semantic-companion" / "px4-sitl"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def unpack(tarball: str | Path | None = None, cache_dir: str | Path | None = None) -> Path:
    """The unpacked SITL folder (the one holding ``run-sih.sh``), unpacking ``tarball`` first
    when this hash was not unpacked before. Safe against concurrent callers (a file lock)."""
    src = tarball_path(tarball)
    if not src.is_file():
        raise Px4SitlError(sitl_available(tarball)[1])
    root = Path(cache_dir) if cache_dir is not None else cache_root()
    root.mkdir(parents=True, exist_ok=True)
    dest = root / _sha256(src)[:16]
    with (root / ".lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (dest / "px4-sitl" / "run-sih.sh").is_file():
            tmp = Path(tempfile.mkdtemp(prefix=".unpack-", dir=root))
            try:
                with tarfile.open(src, "r:gz") as tar:
                    if hasattr(tarfile, "data_filter"):
                        tar.extractall(tmp, filter="data")
                    else:  # Python < 3.11.4: the archive is ours, members are plain files
                        tar.extractall(tmp)
                if not (tmp / "px4-sitl" / "run-sih.sh").is_file():
                    raise Px4SitlError(f"{src}: no px4-sitl/run-sih.sh in the archive")
                shutil.rmtree(dest, ignore_errors=True)
                tmp.rename(dest)
                log.info("PX4 SITL unpacked from %s into %s", src, dest)
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
    return dest / "px4-sitl"


def _udp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


def free_udp_port() -> int:
    """A UDP port that is free on every interface right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("0.0.0.0", 0))
        return int(s.getsockname()[1])


def instance_ports(instance: int) -> tuple[int, ...]:
    """Every UDP port ``run-sih.sh`` uses for ``instance`` (besides the GCS remote port)."""
    return tuple(base + instance for base in _PORT_BASES)


def _claim_instance(exclude: set[int]) -> tuple[int, int]:
    """A free instance number and the open file whose lock claims it for this process: no PX4
    daemon holds its lock, no other caller here claimed it, and all its ports are free."""
    for i in INSTANCES:
        if i in exclude:
            continue
        fd = os.open(f"/tmp/companion-px4-sitl-{i}.lock", os.O_CREAT | os.O_RDWR, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        if _px4_daemon_running(i) or not all(_udp_free(p) for p in instance_ports(i)):
            os.close(fd)
            continue
        return i, fd
    raise Px4SitlError(f"no free PX4 SITL instance in {INSTANCES.start}..{INSTANCES.stop - 1} "
                       "(each needs its UDP ports 14580+i, 14540+i, 18570+i, 19450+i, ... free)")


def _px4_daemon_running(instance: int) -> bool:
    """True while a PX4 daemon holds ``/tmp/px4_lock-<instance>`` (its single-instance lock)."""
    path = Path(f"/tmp/px4_lock-{instance}")
    if not path.exists():
        return False
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)
    return False


class Px4Sitl:
    """One PX4 SITL instance (a context manager; see the module docstring).

    ``tarball``/``cache_dir``: see :func:`unpack`. ``params``: PX4 parameters applied at boot
    (``PX4_PARAM_<NAME>``). ``home_lat_lon_alt``: the SIH home (degrees, degrees, metres AMSL).
    ``gcs_port``: where PX4's GCS link sends (default: a free port). ``workdir``: PX4's working
    folder (parameters, dataman, ``log/*.ulg``, ``px4.log``; default a new temporary folder,
    removed by :meth:`stop` unless start-up failed or ``keep_workdir``). ``lockstep``: run the
    lockstep build (PX4's clock driven by the simulator)."""

    def __init__(self, *, tarball: str | Path | None = None, cache_dir: str | Path | None = None,
                 params: Mapping[str, float | int] | None = None,
                 home_lat_lon_alt: tuple[float, float, float] | None = None, gcs_port: int | None = None,
                 workdir: str | Path | None = None, keep_workdir: bool = False, lockstep: bool = False,
                 ready_timeout_s: float = 150.0) -> None:
        self.tarball = tarball_path(tarball)
        self.cache_dir = cache_dir
        self.params = dict(params or {})
        self.home_lat_lon_alt = home_lat_lon_alt
        self.gcs_port = gcs_port
        self._workdir_arg = Path(workdir) if workdir is not None else None
        self.keep_workdir = keep_workdir
        self.lockstep = lockstep
        self.ready_timeout_s = ready_timeout_s
        self.root: Path | None = None
        self.workdir: Path | None = None
        self.instance: int | None = None
        self._claim_fd: int | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._failed = False
        self.ready_after_s: float | None = None

    # --- life cycle ------------------------------------------------------------------

    def __enter__(self) -> Px4Sitl:
        if self._proc is None:  # entering a SITL started already only takes charge of stopping it
            self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is not None and not issubclass(exc_type, (KeyboardInterrupt, GeneratorExit)):
            self._failed = True
        self.stop()

    def start(self) -> None:
        """Unpack (once), start PX4 on a free instance and wait until it is ready for take-off;
        raises :class:`Px4SitlError` with the log's tail when it exits or is not ready in time."""
        if self._proc is not None:
            raise Px4SitlError("this PX4 SITL is already running")
        self.root = unpack(self.tarball, self.cache_dir)
        self.instance, self._claim_fd = _claim_instance(set())
        if self.gcs_port is None:
            self.gcs_port = free_udp_port()
        try:
            self._spawn()
            self._wait_ready()
        except BaseException:
            self._failed = True
            self.stop()
            raise

    def _spawn(self) -> None:
        assert self.root is not None and self.instance is not None
        if self._workdir_arg is not None:
            self.workdir = self._workdir_arg
            self.workdir.mkdir(parents=True, exist_ok=True)
        else:
            self.workdir = Path(tempfile.mkdtemp(prefix=f"px4-sitl-{self.instance}-"))
        env = {k: v for k, v in os.environ.items() if not k.startswith("PX4_")}
        env.update({"PX4_FRESH": "1", "PX4_WORKDIR": str(self.workdir / "rootfs"), "PX4_MAV_SYS_ID": "1",
                    "PX4_GCS_REMOTE_PORT": str(self.gcs_port)})
        if not self.lockstep:
            env["PX4_NOLOCKSTEP"] = "1"
        if self.home_lat_lon_alt is not None:
            lat, lon, alt = self.home_lat_lon_alt
            env.update({"PX4_HOME_LAT": f"{lat:.8f}", "PX4_HOME_LON": f"{lon:.8f}", "PX4_HOME_ALT": f"{alt:.3f}"})
        for name, value in self.params.items():
            env[f"PX4_PARAM_{name}"] = str(value)
        with self.log_path.open("wb") as out:
            # Its own session: stop() signals the whole group (px4 and the shells its rcS runs).
            self._proc = subprocess.Popen(["sh", str(self.root / "run-sih.sh"), str(self.instance)],
                                          cwd=self.root, env=env, stdout=out, stderr=subprocess.STDOUT,
                                          stdin=subprocess.DEVNULL, start_new_session=True)
        atexit.register(self.stop)
        log.info("PX4 SITL instance %d starting (pid %d, onboard %s, GCS %s, log %s)", self.instance,
                 self._proc.pid, self.onboard_url, self.gcs_url, self.log_path)

    def _wait_ready(self) -> None:
        self.ready_after_s = self._wait_for_line(READY_LINE)
        log.info("PX4 SITL instance %d ready for take-off after %.1f s", self.instance, self.ready_after_s)

    def _wait_for_line(self, line: str, poll_s: float = 0.25) -> float:
        """Block until ``line`` is in PX4's console log; the seconds it took. Raises
        :class:`Px4SitlError` when PX4 exits first or ``ready_timeout_s`` passes."""
        assert self._proc is not None
        t0 = time.monotonic()
        while line not in self.log_text():
            rc = self._proc.poll()
            if rc is not None:
                raise Px4SitlError(f"PX4 SITL instance {self.instance} exited with code {rc} before {line!r}; its "
                                   f"log ({self.log_path}) ends:\n{self.log_tail()}")
            if time.monotonic() - t0 > self.ready_timeout_s:
                raise Px4SitlError(f"PX4 SITL instance {self.instance}: no {line!r} within {self.ready_timeout_s:.0f} "
                                   f"s; its log ({self.log_path}) ends:\n{self.log_tail()}")
            time.sleep(poll_s)
        return time.monotonic() - t0

    def stop(self, timeout_s: float = 5.0) -> None:
        """End PX4 (SIGTERM to its process group, SIGKILL after ``timeout_s``); idempotent."""
        atexit.unregister(self.stop)
        proc, self._proc = self._proc, None
        if proc is not None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                log.warning("PX4 SITL instance %s ignored SIGTERM for %.0f s: killing it", self.instance, timeout_s)
                proc.wait(timeout_s)
            finally:
                # The shells rcS started may outlive px4 itself: the group goes in any case.
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                if proc.poll() is None:
                    proc.wait(timeout_s)
        if self._claim_fd is not None:
            os.close(self._claim_fd)
            self._claim_fd = None
        wd = self.workdir
        if wd is not None and self._workdir_arg is None:
            if self._failed or self.keep_workdir:
                log.info("PX4 SITL log kept in %s", wd)
            else:
                shutil.rmtree(wd, ignore_errors=True)
                self.workdir = None

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    # --- where to talk to it -----------------------------------------------------------

    def _need_instance(self) -> int:
        if self.instance is None:
            raise Px4SitlError("the PX4 SITL has not been started")
        return self.instance

    @property
    def onboard_port(self) -> int:
        """The UDP port PX4's onboard (offboard/API) link sends to: the companion listens here."""
        return 14540 + self._need_instance()

    @property
    def onboard_url(self) -> str:
        """The companion's ``link.url`` for this instance."""
        return f"udpin://127.0.0.1:{self.onboard_port}"

    @property
    def gcs_url(self) -> str:
        """A ground station's (or MAVSDK's) URL: PX4's GCS link sends to this port."""
        self._need_instance()
        return f"udpin://127.0.0.1:{self.gcs_port}"

    @property
    def log_path(self) -> Path:
        """PX4's console output (the commander's and navigator's messages)."""
        if self.workdir is None:
            raise Px4SitlError("the PX4 SITL has no working folder yet")
        return self.workdir / "px4.log"

    def log_text(self) -> str:
        """PX4's console output so far, colour codes removed."""
        try:
            return _ANSI.sub("", self.log_path.read_text(encoding="utf-8", errors="replace"))
        except FileNotFoundError:
            return ""

    def log_tail(self, lines: int = 25) -> str:
        return "\n".join(self.log_text().splitlines()[-lines:])

    def log_lines_since(self, offset: int, pattern: str | None = None) -> list[str]:
        """The log's lines after character ``offset`` (of :meth:`log_text`), those matching
        the regular expression ``pattern`` when given."""
        lines = self.log_text()[offset:].splitlines()
        return [ln for ln in lines if pattern is None or re.search(pattern, ln)]

    # --- PX4's shell commands ----------------------------------------------------------

    def command(self, module: str, *args: str, timeout_s: float = 15.0) -> str:
        """Run ``px4-<module> --instance i ARGS`` against the running daemon; its output
        (colour codes removed). Raises :class:`Px4SitlError` when it fails."""
        if not self.running or self.root is None:
            raise Px4SitlError(f"px4-{module}: the PX4 SITL is not running")
        binary = self.root / ("bin" if self.lockstep else "bin-nolockstep") / f"px4-{module}"
        try:
            res = subprocess.run([str(binary), "--instance", str(self._need_instance()), *args],
                                 capture_output=True, timeout=timeout_s, check=False, stdin=subprocess.DEVNULL)
        except subprocess.TimeoutExpired as exc:
            raise Px4SitlError(f"px4-{module} {' '.join(args)}: no answer within {timeout_s:.0f} s") from exc
        out = _ANSI.sub("", res.stdout.decode(errors="replace") + res.stderr.decode(errors="replace"))
        if res.returncode != 0:
            raise Px4SitlError(f"px4-{module} {' '.join(args)} failed (exit {res.returncode}): {out.strip()[-500:]}")
        return out

    def uorb_top_hz(self, topics: list[str]) -> dict[str, float]:
        """Each topic's publication rate over one second as PX4's ``uorb top`` sees it (Hz;
        a topic never published is 0). Instances of a topic are summed."""
        out = self.command("uorb", "top", "-1", *topics)
        rates = dict.fromkeys(topics, 0.0)
        for line in out.splitlines():
            parts = line.split()
            # TOPIC NAME  INST #SUB RATE #Q SIZE
            if len(parts) >= 4 and parts[0] in rates and parts[1].isdigit():
                with contextlib.suppress(ValueError):
                    rates[parts[0]] += float(parts[3])
        return rates

    def listener(self, topic: str, count: int = 1) -> str:
        """``listener TOPIC -n COUNT``: the topic's latest messages as text."""
        return self.command("listener", topic, "-n", str(count))

    def commander_status(self) -> str:
        return self.command("commander", "status")

    def param_set(self, name: str, value: float | int) -> None:
        """Set a PX4 parameter in the running instance."""
        self.command("param", "set", name, str(value))

    def param_get(self, name: str) -> float:
        """A PX4 parameter's current value."""
        out = self.command("param", "show", name)
        m = re.search(rf"{re.escape(name)}\s*\[[^\]]*\]\s*:\s*(-?[0-9.eE+-]+)", out)
        if m is None:
            raise Px4SitlError(f"param show {name}: no value in {out.strip()[-300:]!r}")
        return float(m.group(1))

    def mavlink_stream(self, udp_port: int, message: str, rate_hz: float) -> None:
        """Stream ``message`` at ``rate_hz`` on the MAVLink instance bound to ``udp_port``."""
        self.command("mavlink", "stream", "-u", str(udp_port), "-s", message, "-r", f"{rate_hz:g}")
