"""``Accept`` header negotiation (RFC 9110 section 12.5.1): media ranges with q-values.

``choose_media_type(accept, offered)`` picks the offered type the client prefers: each offered
type takes the q of the most specific range that matches it (``type/subtype`` over ``type/*``
over ``*/*``); the highest q wins; ties go to the type named explicitly over one matched by a
wildcard, then to the server's order of ``offered``. A missing or empty header accepts anything
(the first offered type); a header none of whose ranges accepts an offered type (all q=0, or only
other types) gives None: the caller answers 406. Parameters other than q (``charset=...``) are
ignored; a malformed range or q is skipped, never an error.
"""

from __future__ import annotations

from collections.abc import Sequence


def parse_accept(header: str | None) -> list[tuple[str, str, float]]:
    """(type, subtype, q) of each well-formed media range of an ``Accept`` header, lower case,
    in header order; q defaults to 1 and is clipped to [0, 1]."""
    out = []
    for part in (header or "").split(","):
        fields = [f.strip() for f in part.split(";")]
        media = fields[0].lower()
        kind, sep, sub = media.partition("/")
        if not sep or not kind or not sub or " " in media or (kind == "*" and sub != "*"):
            continue
        q = 1.0
        ok = True
        for param in fields[1:]:
            name, eq, value = param.partition("=")
            if eq and name.strip().lower() == "q":
                try:
                    q = float(value.strip().strip('"'))
                except ValueError:
                    ok = False
                if q != q:  # NaN
                    ok = False
                q = min(max(q, 0.0), 1.0)
        if ok:
            out.append((kind, sub, q))
    return out


def choose_media_type(accept: str | None, offered: Sequence[str]) -> str | None:
    """The offered media type the ``accept`` header prefers, or None when it accepts none of
    them (see the module docstring)."""
    ranges = parse_accept(accept)
    if not ranges:
        return offered[0] if offered else None
    best: tuple[float, int, int] | None = None
    choice = None
    for order, media in enumerate(offered):
        kind, _, sub = media.lower().partition("/")
        q, specificity = None, -1
        for rk, rs, rq in ranges:
            if rk == kind and rs == sub:
                spec = 2
            elif rk == kind and rs == "*":
                spec = 1
            elif rk == "*" and rs == "*":
                spec = 0
            else:
                continue
            if spec > specificity:
                q, specificity = rq, spec
        if q is None or q <= 0.0:
            continue
        rank = (q, specificity, -order)
        if best is None or rank > best:
            best, choice = rank, media
    return choice
