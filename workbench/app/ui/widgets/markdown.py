"""Text from elsewhere (error messages, object names, file paths) put into the panel's Markdown literally."""

from __future__ import annotations

import re

_SPECIAL = re.compile(r"([\\`*_{}\[\]<>()#+!|~])")


def escape(text: object) -> str:
    """``text`` with every Markdown control character backslash-escaped: "'_' or '-'" keeps its underscore
    (unescaped, a lone '_' began an emphasis and vanished)."""
    return _SPECIAL.sub(r"\\\1", str(text))
