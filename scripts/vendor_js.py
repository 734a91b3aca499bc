"""Vendor the report's JavaScript from the npm registry: pinned tarballs, integrity checked.

Run from the repository root: ``python scripts/vendor_js.py``. Each package in ``PINNED`` is
downloaded at its pinned version, its tarball checked against the registry's ``sha512``
integrity string (Subresource Integrity format), and the listed files written into
``canopy_kit/report/vendor/`` (with the package's licence), with ``VENDORED.json`` naming
the version and hash of each. The report inlines them, so the page needs no network.
"""

from __future__ import annotations

import base64
import hashlib
import io
import json
import sys
import tarfile
import urllib.request
from pathlib import Path

VENDOR = Path(__file__).resolve().parents[1] / "canopy_kit" / "report" / "vendor"
REGISTRY = "https://registry.npmjs.org"

# package -> (version, integrity, {file in the tarball: name in vendor/})
PINNED = {
    "plotly.js-dist-min": (
        "4.1.2",
        "sha512-VSmS9KVNun16S8qFYYp9LlL/XBby4ueeGqB+K9AqRCVsup8dSpGULap4UyR1f2mz4pV3qjWp1sR5chwLgIKPoQ==",
        {"package/plotly.min.js": "plotly.min.js", "package/LICENSE": "plotly.LICENSE.txt"},
    ),
}


def integrity(data: bytes) -> str:
    """The SRI ``sha512-<base64>`` string of ``data`` (what npm's ``dist.integrity`` holds)."""
    return "sha512-" + base64.b64encode(hashlib.sha512(data).digest()).decode()


def tarball_url(package: str, version: str) -> str:
    """Where the registry keeps ``package``'s tarball at ``version``."""
    return f"{REGISTRY}/{package}/-/{package.rsplit('/', 1)[-1]}-{version}.tgz"


def vendor(package: str, version: str, expected: str, files: dict[str, str]) -> dict[str, str]:
    """Download, check and unpack one pinned package; returns its VENDORED.json entry."""
    url = tarball_url(package, version)
    with urllib.request.urlopen(url, timeout=120) as resp:
        data = resp.read()
    got = integrity(data)
    if got != expected:
        raise SystemExit(
            f"{package}@{version}: integrity mismatch\n  expected {expected}\n  got      {got}"
        )
    VENDOR.mkdir(parents=True, exist_ok=True)
    sha256 = {}
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
        for member, name in files.items():
            fh = tar.extractfile(member)
            if fh is None:
                raise SystemExit(f"{package}@{version}: {member} missing from the tarball")
            content = fh.read()
            tmp = VENDOR / f".{name}.tmp"
            tmp.write_bytes(content)
            tmp.replace(VENDOR / name)
            sha256[name] = hashlib.sha256(content).hexdigest()
    return {
        "version": version,
        "integrity": expected,
        "tarball": url,
        "files": dict(sorted(sha256.items())),
    }


def main() -> int:
    """Vendor every pinned package and write VENDORED.json."""
    record = {pkg: vendor(pkg, *spec) for pkg, spec in PINNED.items()}
    tmp = VENDOR / ".VENDORED.json.tmp"
    tmp.write_text(json.dumps(record, indent=2) + "\n")
    tmp.replace(VENDOR / "VENDORED.json")
    for pkg, rec in record.items():
        print(f"{pkg}@{rec['version']}: {', '.join(rec['files'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
