"""Reading the files a user hands the tools, strictly.

Every reader of an input file (configuration, calibration, pose table,
sweep output, frame log, capture) goes through this module, so a damaged
file is refused the same way everywhere: one :class:`InputFileError`, a
``ValueError`` whose message is one line naming the file and, where there
is one, the line or key; ``coiltrack`` (``tools/cli.py``) prints it and
exits with status 2, without a traceback.

* :func:`read_text`: the file as UTF-8 text, or the error saying what it
  is instead (UTF-16 or UTF-32 by its byte-order mark or its NUL bytes;
  otherwise the first byte that is not UTF-8, by line and column: a file
  saved as latin-1 or cp1252 with a degree sign in a comment).
* :func:`load_toml`: a TOML file (duplicated keys refused by ``tomllib``,
  the line named) whose numbers are all finite (``nan`` and ``inf`` refused,
  the key named).
* :func:`loads_json` / :func:`load_json`: strict JSON: no ``NaN`` or
  ``Infinity``, no key given twice in one object.
* :func:`text_lines`: a line-oriented file as ``(number, text)``, stopping
  at the first line that is not UTF-8, and telling whether the last line
  lacks its newline (a file cut short).
* :func:`warn`: the one warning line of a file used up to its damage.
"""
from __future__ import annotations

import json
import math
import re
import sys

#: byte-order marks of the encodings a text editor may save in instead of UTF-8
_BOMS = ((b"\xff\xfe\x00\x00", "UTF-32"), (b"\x00\x00\xfe\xff", "UTF-32"),
         (b"\xff\xfe", "UTF-16"), (b"\xfe\xff", "UTF-16"))
_UTF8_BOM = b"\xef\xbb\xbf"


class InputFileError(ValueError):
    """An input file that cannot be used: unreadable, not UTF-8, empty, cut short, or a
    value of the wrong type, not finite, or given twice. ``str()`` is one line:
    ``PATH: line N: what`` or ``PATH: key 'K': what`` (or ``PATH: what``)."""

    def __init__(self, path, message: str, line: int | None = None, key: str | None = None):
        self.path = str(path)
        self.message = message
        self.line = line
        self.key = key
        where = f"line {line}: " if line is not None else f"key '{key}': " if key is not None else ""
        super().__init__(f"{self.path}: {where}{message}")

    def __reduce__(self):
        """Picklable (a worker process can hand it back)."""
        return (InputFileError, (self.path, self.message, self.line, self.key))


def read_bytes(path) -> bytes:
    """The file's bytes, or :class:`InputFileError` (missing, a directory, unreadable)."""
    try:
        with open(path, "rb") as fh:
            return fh.read()
    except OSError as exc:
        raise InputFileError(path, f"cannot read it: {exc.strerror or exc}") from None


def _position(data: bytes, offset: int) -> tuple[int, int]:
    """(line, column), both from 1, of byte ``offset``."""
    line = data.count(b"\n", 0, offset) + 1
    return line, offset - (data.rfind(b"\n", 0, offset) + 1) + 1


def _without_bom(data: bytes, path) -> bytes:
    """``data`` without a UTF-8 byte-order mark; :class:`InputFileError` for a UTF-16/32 one."""
    if data.startswith(_UTF8_BOM):
        data = data[len(_UTF8_BOM):]
    for bom, name in _BOMS:
        if data.startswith(bom):
            raise InputFileError(path, f"is {name} text, not UTF-8: save it as UTF-8")
    return data


def decode_utf8(data: bytes, path) -> str:
    """``data`` as UTF-8 text (a UTF-8 byte-order mark dropped), or :class:`InputFileError`
    naming the encoding it is in instead or the first byte that is not UTF-8."""
    data = _without_bom(data, path)
    nul = data.find(b"\x00")
    if nul >= 0:
        line, col = _position(data, nul)
        hint = " (UTF-16 text? save it as UTF-8)" if nul < 4 or data[1::2].count(0) > len(data) // 4 else ""
        raise InputFileError(path, f"a NUL byte at column {col}: not a text file{hint}", line=line)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line, col = _position(data, exc.start)
        raise InputFileError(path, f"byte {data[exc.start]:#04x} at column {col} is not UTF-8 (saved as latin-1 "
                                   "or another code page? save it as UTF-8)", line=line) from None


def read_text(path) -> str:
    """The file as UTF-8 text; :class:`InputFileError` otherwise (see :func:`decode_utf8`)."""
    return decode_utf8(read_bytes(path), path)


def require_content(text: str, path, what: str) -> None:
    """Refuse a file with nothing but white space in it."""
    if not text.strip():
        raise InputFileError(path, f"is empty: no {what} in it")


def nonfinite_key(obj, prefix: str = "") -> str | None:
    """The dotted key (``a.b[2]``) of the first number in ``obj`` that is nan or infinite, or None."""
    if isinstance(obj, float):
        return None if math.isfinite(obj) else (prefix or "<value>")
    if isinstance(obj, dict):
        for k, v in obj.items():
            found = nonfinite_key(v, f"{prefix}.{k}" if prefix else str(k))
            if found:
                return found
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            found = nonfinite_key(v, f"{prefix}[{i}]")
            if found:
                return found
    return None


def _lookup(obj, dotted: str):
    for part in re.findall(r"[^.\[\]]+|\[\d+\]", dotted):
        obj = obj[int(part[1:-1])] if part.startswith("[") else obj[part]
    return obj


def refuse_nonfinite(obj, path) -> None:
    """:class:`InputFileError` naming the first key whose number is nan or infinite."""
    key = nonfinite_key(obj)
    if key is not None:
        raise InputFileError(path, f"must be a finite number, got {_lookup(obj, key) if key != '<value>' else obj}",
                             key=key)


def loads_toml(text: str, path) -> dict:
    """Parse TOML text of ``path``; a syntax error (a key given twice included) names its line,
    and a ``nan`` or ``inf`` its key."""
    import tomllib

    try:
        d = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        m = re.search(r"\(at line (\d+), column (\d+)\)$", str(exc))
        msg = str(exc)[:m.start()].strip() if m else str(exc)
        line = int(m.group(1)) if m else None
        if not m and str(exc).endswith("(at end of document)"):
            msg = str(exc)[:-len("(at end of document)")].strip() + " at the end of the file (cut short?)"
            line = text.count("\n") + 1
        if "overwrite" in msg:
            msg += " (a key or table given twice)"
        raise InputFileError(path, f"not valid TOML: {msg}" + (f" (column {m.group(2)})" if m else ""),
                             line=line) from None
    refuse_nonfinite(d, path)
    return d


def load_toml(path, what: str | None = None) -> dict:
    """A TOML file, strictly (:func:`read_text`, :func:`loads_toml`); with ``what``, an empty
    file is refused as holding no ``what``."""
    text = read_text(path)
    if what is not None:
        require_content(text, path, what)
    return loads_toml(text, path)


def _no_duplicates(pairs):
    d = {}
    for k, v in pairs:
        if k in d:
            raise _Duplicate(k)
        d[k] = v
    return d


class _Duplicate(ValueError):
    def __init__(self, key):
        super().__init__(key)
        self.key = key


def _constant(name):
    raise _NonFinite(name)


class _NonFinite(ValueError):
    def __init__(self, name):
        super().__init__(name)
        self.name = name


def loads_json(text: str, path, line: int | None = None):
    """Parse JSON text of ``path`` (``line``: the line of the file it is, for a JSON-lines
    file) strictly: no ``NaN``/``Infinity``, no key twice in an object."""
    try:
        return json.loads(text, object_pairs_hook=_no_duplicates, parse_constant=_constant)
    except _Duplicate as exc:
        if line is None:
            raise InputFileError(path, "given twice in one object", key=exc.key) from None
        raise InputFileError(path, f"key '{exc.key}' given twice in one object", line=line) from None
    except _NonFinite as exc:
        raise InputFileError(path, f"{exc.name} is not a finite number (JSON has none)", line=line) from None
    except json.JSONDecodeError as exc:
        where = exc.lineno if line is None else line
        raise InputFileError(path, f"not valid JSON: {exc.msg} (column {exc.colno})", line=where) from None
    except RecursionError:
        raise InputFileError(path, "not valid JSON: nested too deeply", line=line) from None


def load_json(path, what: str | None = None):
    """A JSON file, strictly (:func:`read_text`, :func:`loads_json`)."""
    text = read_text(path)
    if what is not None:
        require_content(text, path, what)
    return loads_json(text, path)


def text_lines(data: bytes, path):
    """``(lines, damage)`` of a line-oriented file: ``lines`` the ``(number, text)`` of each
    line (newline dropped) up to the first that is not UTF-8, and ``damage`` None for a whole
    file, else ``(line number, what)``: that line is not UTF-8, or the last line has no
    newline (the file was cut short there)."""
    data = _without_bom(data, path)
    raw = data.split(b"\n")
    cut = raw[-1] != b""
    if not cut:
        raw.pop()
    lines = []
    for n, b in enumerate(raw, 1):
        if cut and n == len(raw):
            return lines, (n, "cut short (no newline at its end)")
        try:
            text = b.decode("utf-8")
        except UnicodeDecodeError as exc:
            return lines, (n, f"byte {b[exc.start]:#04x} at column {exc.start + 1} is not UTF-8")
        if "\x00" in text:
            return lines, (n, f"a NUL byte at column {text.index(chr(0)) + 1}")
        lines.append((n, text[:-1] if text.endswith("\r") else text))
    return lines, None


def warn(command: str, path, message: str) -> None:
    """The one line on standard error of a file used up to its damage."""
    print(f"coiltrack {command}: warning: {path}: {message}", file=sys.stderr)
