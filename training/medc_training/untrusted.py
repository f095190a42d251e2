"""What every reader of data from strangers shares: the bundle size ceiling and the text filter.

Torch-free, so the registry (which fetches and caches bundles), the agents (which load them) and
the bundle loader itself import one value and one helper instead of keeping copies in step.
"""

from __future__ import annotations

#: The largest policy bundle anything in MEDC fetches, caches or loads: the bundle loader's file
#: ceiling, the registry's content limit (``medc_registry.cid.MAX_CONTENT_BYTES``) and the agents'
#: check. A shipped bundle is 0.1-2.4 MB; the largest architecture the caps allow is far below this.
MAX_BUNDLE_BYTES = 256 << 20


def printable(text: str, limit: int, drop: str = "") -> str:
    """``text`` with anything but printable ASCII (and any character in ``drop``, e.g. quotes)
    shown as ``?``, cut to ``limit`` characters with ``...`` marking a cut: safe to put in a
    message, a log line or on a terminal whatever a file or a topic message held."""
    clean = "".join(ch if " " <= ch <= "~" and ch not in drop else "?" for ch in text[:limit + 1])
    return clean if len(clean) <= limit else clean[:limit] + "..."
