"""A real Mosquitto broker for integration tests, on a free loopback port.

``MosquittoBroker(workdir).start()`` writes a config (persistence off, listener on
127.0.0.1 only, optional password file, ACL and TLS), starts ``mosquitto -c`` and waits
until it accepts TCP connections. ``stop()`` kills it; ``start()`` again reuses the port, so a
test can restart the broker under a connected client. Also: :func:`make_tls_files` builds a
throwaway CA and a server certificate for 127.0.0.1 with the ``openssl`` command.

CI installs the ``mosquitto`` Debian package: a missing binary fails the test, it does not
skip it.
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

MOSQUITTO = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
MOSQUITTO_PASSWD = shutil.which("mosquitto_passwd") or "/usr/bin/mosquitto_passwd"
OPENSSL = shutil.which("openssl") or "/usr/bin/openssl"


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _require(path: str, package: str) -> None:
    if not Path(path).exists():
        pytest.fail(f"{path} not found: install the Debian package {package!r} (make test does)")


@dataclass(frozen=True)
class TlsFiles:
    """PEM files of a test CA and a server certificate valid for 127.0.0.1 and localhost."""

    ca_cert: Path
    server_cert: Path
    server_key: Path


def make_tls_files(workdir: Path, name: str = "test") -> TlsFiles:
    """A fresh CA and a server certificate signed by it (EC P-256, valid two days)."""
    _require(OPENSSL, "openssl")
    d = workdir / f"tls-{name}"
    d.mkdir(parents=True, exist_ok=True)
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]

    def run(*args: str) -> None:
        subprocess.run([OPENSSL, *args], cwd=d, check=True, capture_output=True)

    run("req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.crt", "-days", "2",
        "-subj", f"/CN={name} test CA")
    run("req", *ec, "-keyout", "server.key", "-out", "server.csr", "-subj", "/CN=localhost")
    (d / "server.ext").write_text(
        "subjectAltName=IP:127.0.0.1,DNS:localhost\n"
        "basicConstraints=CA:FALSE\n"
        "keyUsage=digitalSignature,keyEncipherment\n"
        "extendedKeyUsage=serverAuth\n"
    )
    run("x509", "-req", "-in", "server.csr", "-CA", "ca.crt", "-CAkey", "ca.key",
        "-CAcreateserial", "-out", "server.crt", "-days", "2", "-extfile", "server.ext")
    return TlsFiles(d / "ca.crt", d / "server.crt", d / "server.key")


class MosquittoBroker:
    """One mosquitto process with a generated config (see the module doc).

    ``passwords``: user -> password (anonymous access is then refused). ``acl``: the text
    of an ACL file. ``tls``: serve TLS instead of plain TCP.
    """

    def __init__(
        self,
        workdir: Path,
        *,
        passwords: dict[str, str] | None = None,
        acl: str | None = None,
        tls: TlsFiles | None = None,
    ) -> None:
        _require(MOSQUITTO, "mosquitto")
        self.workdir = workdir
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.host = "127.0.0.1"
        self.port = free_port()
        self.log_path = workdir / "mosquitto.log"
        self._proc: subprocess.Popen[bytes] | None = None
        lines = [
            f"listener {self.port} {self.host}",
            "persistence false",
            "log_type error",
            "log_type warning",
            "log_type notice",
            "log_type information",
        ]
        # As root, mosquitto drops to its own user, which cannot read pytest's 0700 folders.
        if os.geteuid() == 0:
            lines.append(f"user {pwd.getpwuid(os.geteuid()).pw_name}")
        if passwords:
            _require(MOSQUITTO_PASSWD, "mosquitto")
            pw_file = workdir / "passwords"
            pw_file.unlink(missing_ok=True)
            for i, (user, password) in enumerate(passwords.items()):
                flags = ["-b", "-c"] if i == 0 else ["-b"]
                subprocess.run([MOSQUITTO_PASSWD, *flags, str(pw_file), user, password],
                               check=True, capture_output=True)
            lines += ["allow_anonymous false", f"password_file {pw_file}"]
        else:
            lines.append("allow_anonymous true")
        if acl is not None:
            acl_file = workdir / "acl"
            acl_file.write_text(acl)
            lines.append(f"acl_file {acl_file}")
        if tls is not None:
            lines += [f"cafile {tls.ca_cert}", f"certfile {tls.server_cert}",
                      f"keyfile {tls.server_key}"]
        self.config_path = workdir / "mosquitto.conf"
        self.config_path.write_text("\n".join(lines) + "\n")

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def start(self, timeout_s: float = 10.0) -> "MosquittoBroker":
        """Start the broker and wait until its port accepts connections."""
        if self.running:
            return self
        with self.log_path.open("ab") as log:
            self._proc = subprocess.Popen(
                [MOSQUITTO, "-c", str(self.config_path)], stdout=log, stderr=subprocess.STDOUT
            )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._proc.poll() is not None:
                pytest.fail(f"mosquitto exited with {self._proc.returncode}:\n{self.log()}")
            try:
                with socket.create_connection((self.host, self.port), timeout=0.5):
                    return self
            except OSError:
                time.sleep(0.05)
        self.stop()
        pytest.fail(f"mosquitto did not listen on {self.host}:{self.port}:\n{self.log()}")

    def stop(self) -> None:
        """Kill the broker (as a crash would: no goodbye to clients) and wait for it."""
        if self._proc is None:
            return
        if self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait(timeout=10)
        self._proc = None

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""
