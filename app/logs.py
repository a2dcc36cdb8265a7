"""The process's logging: timestamps and levels, text or JSON lines, no API key ever printed."""

from __future__ import annotations

import json
import logging
import re
import sys
import time
from typing import Any
from urllib.parse import unquote

LEVELS = ("debug", "info", "warning", "error")
FORMATS = ("text", "json")

# A key is `eqgw_` and 43 URL-safe characters; a URL may carry one as `?key=` (old links, the
# websocket of old clients). Both are masked in every record, whoever logs it, also when
# percent-encoded (`?%6Bey=eqgw%5F...` is what the server decodes to `?key=eqgw_...`).
_KEY = re.compile(r"eqgw_[A-Za-z0-9_-]{8,}", re.I)
_KEY_PARAM = re.compile(r"([?&](?:api_)?key=)[^&\s\"']+", re.I)
_ENCODED = re.compile(r"%[0-9A-Fa-f]{2}")
_DECODINGS = 3  # a URL encoded this many times over is still decoded


def _redact_plain(text: str) -> str:
    return _KEY.sub("eqgw_***", _KEY_PARAM.sub(r"\1***", text))


def redact(text: str) -> str:
    """`text` with API keys and `key=` query values replaced by `***`, looked for in the text
    and in its percent-decodings; where a decoding reveals one, the decoded text is returned,
    masked."""
    masked = _redact_plain(text)
    decoded = text
    for _ in range(_DECODINGS):
        if not _ENCODED.search(decoded):
            break
        decoded = unquote(decoded)
        plain = _redact_plain(decoded)
        if plain != decoded:
            return plain
    return masked


class RedactKeys(logging.Filter):
    """Masks API keys in a record's message and arguments (uvicorn's access log passes the
    path with its query string as an argument)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(redact(a) if isinstance(a, str) else a for a in record.args)
        elif isinstance(record.args, dict):
            args = record.args.items()
            record.args = {k: redact(v) if isinstance(v, str) else v for k, v in args}
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time (UTC, ISO 8601), level, logger, message[, exc]."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
            + f".{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
        }
        if record.exc_info:
            out["exc"] = redact(self.formatException(record.exc_info))
        return json.dumps(out, ensure_ascii=False)


TEXT_FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"


def configure_logging(level: str = "warning", fmt: str = "text") -> None:
    """Send every logger's records at `level` and above to stderr in `fmt` (text or json)."""
    handler = logging.StreamHandler(sys.stderr)
    if fmt == "json":
        handler.setFormatter(JsonFormatter())
    else:
        formatter = logging.Formatter(TEXT_FORMAT, "%Y-%m-%dT%H:%M:%S%z")
        handler.setFormatter(formatter)
    handler.addFilter(RedactKeys())
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level.upper())
