"""Small helpers for writing generated sections of markdown docs and files atomically."""

from __future__ import annotations

from pathlib import Path


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` via a temporary file in the same folder and ``os.replace``."""
    from renderer.imageio import atomic_write_bytes

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, text.encode("utf-8"))


def replace_section(path: Path, key: str, body: str) -> None:
    """Replace the generated block ``<!-- begin:key -->…<!-- end:key -->`` of a markdown file
    (appending it when absent), leaving hand-written text around it untouched."""
    path = Path(path)
    begin, end = f"<!-- begin:{key} -->", f"<!-- end:{key} -->"
    text = path.read_text() if path.exists() else ""
    block = f"{begin}\n{body}\n{end}"
    if begin in text and end in text:
        pre, rest = text.split(begin, 1)
        _, post = rest.split(end, 1)
        text = pre + block + post
    else:
        text = (text.rstrip() + "\n\n" if text else "") + block + "\n"
    atomic_write_text(path, text)
