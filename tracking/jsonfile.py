"""Read a user-supplied JSON file, turning every failure into one clear error naming the file."""

import json
from pathlib import Path


def read_json(path: str | Path, error: type[Exception], what: str):
    """Parsed JSON of `path`; raises `error` ("cannot read <what> file ..." / "not valid JSON")."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise error(f"cannot read {what} file {path}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:  # bytes that are not text (a damaged or binary file)
        raise error(f"{path}: not a text (JSON) file ({exc})") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(f"{path}: not valid JSON ({exc})") from None
