"""Everything ``pip install -e .[dev]`` pulls in allows commercial use.

Walks the requirement closure of ``selfcal[dev]`` in this environment (installed
metadata, markers and extras evaluated) and reads each distribution's licence metadata
and licence files. A licence that forbids commercial use fails the test, with its name.
"""

import importlib.metadata as md
import re

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

FORBIDDING = re.compile(
    r"non[- ]?commercial (use|purposes?|research)|academic use licen[cs]e|academic non[- ]?commercial"
    r"|not for (use by )?(consumers or )?commercial|CC[- ]BY[- ]NC"
    r"|commons clause|business source licen[cs]e|server side public licen[cs]e|\bSSPL\b|polyform[- ]noncommercial",
    re.IGNORECASE,
)


def closure(root: str, extras: set[str]) -> dict[str, md.Distribution]:
    """Installed distributions required by ``root[extras]``, by canonical name."""
    seen: dict[str, md.Distribution] = {}
    todo = [(root, frozenset(extras))]
    done = set()
    while todo:
        name, ex = todo.pop()
        key = (canonicalize_name(name), ex)
        if key in done:
            continue
        done.add(key)
        try:
            dist = md.distribution(name)
        except md.PackageNotFoundError:
            continue  # an optional requirement whose marker did not apply on install
        seen[canonicalize_name(name)] = dist
        for text in dist.requires or []:
            req = Requirement(text)
            envs = [{"extra": e} for e in ex] or [{"extra": ""}]
            if req.marker is not None and not any(req.marker.evaluate(env) for env in envs):
                continue
            todo.append((req.name, frozenset(req.extras)))
    return seen


def licence_texts(dist: md.Distribution) -> list[str]:
    meta = dist.metadata
    texts = [meta.get("License") or "", meta.get("License-Expression") or ""]
    texts += [c for c in meta.get_all("Classifier") or [] if c.startswith("License")]
    for f in dist.files or []:
        name = f.name.upper()
        if name.startswith(("LICENSE", "LICENCE", "COPYING", "NOTICE")) and ".dist-info" in str(f):
            try:
                texts.append(f.locate().read_text(encoding="utf-8", errors="replace")[:20000])
            except (OSError, UnicodeError):
                pass
    return texts


def test_dev_install_has_no_licence_that_forbids_commercial_use():
    deps = closure("selfcal", {"dev"})
    assert len(deps) > 20, sorted(deps)  # the closure really was walked
    bad = {}
    for name, dist in deps.items():
        for text in licence_texts(dist):
            m = FORBIDDING.search(text)
            if m:
                bad[name] = m.group(0)
                break
    assert not bad, f"licences that forbid commercial use: {bad}"
    assert "actipy" not in deps


def test_the_checker_catches_a_non_commercial_licence():
    assert FORBIDDING.search("THE SOFTWARE IS INTENDED FOR USE BY ACADEMICS ... NOT FOR USE BY CONSUMERS OR COMMERCIAL")
    assert FORBIDDING.search("Academic Use Licence")
    assert FORBIDDING.search("License :: Free for non-commercial use")
    # permissive and copyleft texts that mention the word are not refusals
    assert not FORBIDDING.search("exploited by anyone for any purpose, commercial or non-commercial, and in any way")
    assert not FORBIDDING.search("This alternative is allowed only for noncommercial distribution")
    assert not FORBIDDING.search("MIT License") and not FORBIDDING.search("Apache Software License")
