"""Certificates for TLS tests, made with the ``openssl`` command as docs/scaling-out.md shows: a CA, and a
certificate it signs for a set of IP addresses."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path


def unavailable() -> str | None:
    return None if shutil.which("openssl") else "the `openssl` command is not installed"


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def make_ca(where: Path, name: str) -> Path:
    """``where/<name>.pem`` (and its key, ``<name>-key.pem``): a self-signed CA."""
    where.mkdir(parents=True, exist_ok=True)
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-keyout",
             f"{name}-key.pem", "-out", f"{name}.pem", "-days", "2", "-subj", f"/CN={name}", cwd=where)
    return where / f"{name}.pem"


def make_cert(where: Path, ca: Path, name: str, ips: list[str], dns: list[str] = ()) -> tuple[Path, Path]:
    """``(certificate, key)`` for ``name``, signed by ``ca`` (made by :func:`make_ca`), valid for ``ips`` and the
    host names ``dns``."""
    _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-keyout",
             f"{name}-key.pem", "-out", f"{name}.csr", "-subj", f"/CN={name}", cwd=where)
    names = [f"IP:{ip}" for ip in ips] + [f"DNS:{host}" for host in dns]
    (where / f"{name}.ext").write_text("subjectAltName=" + ",".join(names) + "\n")
    _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", str(ca), "-CAkey", str(ca.with_name(ca.stem + "-key.pem")),
             "-CAcreateserial", "-out", f"{name}.pem", "-days", "2", "-extfile", f"{name}.ext", cwd=where)
    return where / f"{name}.pem", where / f"{name}-key.pem"


def zenoh_tls(path: Path, ca: Path | None, cert: tuple[Path, Path] | None = None) -> Path:
    """A Zenoh config file at ``path`` naming ``ca`` (None: no root_ca_certificate) and, for a host that
    listens, its certificate and key."""
    tls = {}
    if ca is not None:
        tls["root_ca_certificate"] = str(ca)
    if cert is not None:
        tls["listen_certificate"], tls["listen_private_key"] = str(cert[0]), str(cert[1])
    body = ", ".join(f'{k}: "{v}"' for k, v in tls.items())
    path.write_text(f"{{ transport: {{ link: {{ tls: {{ {body} }} }} }} }}\n")
    return path
