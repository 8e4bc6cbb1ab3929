"""MkDocs hook: the site loads no script from a network.

The theme draws ```mermaid blocks with Mermaid, which it fetches from a CDN unless a ``mermaid`` is
already defined on the page. This hook serves Mermaid from the site itself: the official npm package,
pinned by version and by the registry's SHA-512 integrity, is fetched once from the npm registry
(the set-up does it; a later build needs no network), unpacked into ``build/vendor/`` (ignored by
git) and copied into the site as ``js/mermaid.min.js``, which every page loads before the theme.
"""

from __future__ import annotations

import base64
import hashlib
import io
import shutil
import tarfile
import urllib.request
from pathlib import Path

MERMAID_VERSION = "12.3.0"
#: the npm registry's ``dist.integrity`` of mermaid-12.3.0.tgz
MERMAID_INTEGRITY = "sha512-4113TdXeLAsMruJ79OpFL5O8+LTFXhQqZ260rF3tgUmiNAtRm4Uume04I+65PRN6yZ69J4f8rVYWW8zRk65UYw=="
MERMAID_URL = f"https://registry.npmjs.org/mermaid/-/mermaid-{MERMAID_VERSION}.tgz"
VENDOR = Path(__file__).resolve().parents[1] / "build" / "vendor"
SITE_PATH = "js/mermaid.min.js"


def mermaid_script(vendor: Path = VENDOR, url: str = MERMAID_URL) -> Path:
    """``mermaid.min.js`` of the pinned version: from the vendor folder, else fetched once and checked."""
    path = vendor / f"mermaid-{MERMAID_VERSION}" / "mermaid.min.js"
    if path.is_file():
        return path
    try:
        with urllib.request.urlopen(url, timeout=120) as r:
            data = r.read()
    except OSError as exc:
        raise SystemExit(
            f"the docs need Mermaid {MERMAID_VERSION} in {path.parent} and could not fetch it from {url} ({exc}); "
            "run `bash scripts/setup.sh` once where the npm registry is reachable"
        ) from None
    digest = "sha512-" + base64.b64encode(hashlib.sha512(data).digest()).decode()
    if digest != MERMAID_INTEGRITY:
        raise SystemExit(f"{url}: integrity {digest} is not the pinned {MERMAID_INTEGRITY}; refusing it")
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
        member = tar.extractfile("package/dist/mermaid.min.js")
        if member is None:
            raise SystemExit(f"{url}: no package/dist/mermaid.min.js in the package")
        script = member.read()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".partial")
    tmp.write_bytes(script)
    tmp.replace(path)
    return path


def on_config(config):
    mermaid_script()
    if SITE_PATH not in [str(s) for s in config.extra_javascript]:
        config.extra_javascript.insert(0, SITE_PATH)
    return config


def on_post_build(config):
    target = Path(config.site_dir) / SITE_PATH
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(mermaid_script(), target)


if __name__ == "__main__":  # the set-up fetches it: `python3 docs/offline.py`
    print(mermaid_script())
