"""Material files (format `metarig-material/1`): ligament, contact, inertia and damping constants, SI.

A TOML (or JSON, same structure) document::

    format = "metarig-material/1"
    source = "where the values come from"
    created = "2026-05-10T12:00:00Z"
    notes = "free text"

    [parameters.k_shear]
    value = 1190.0        # SI, in the unit below
    stderr = 25.0         # optional standard error, same unit
    unit = "N/m"          # optional on reading; must be SI_UNITS[name] when given

A parameter may also be a bare number (`k_shear = 1190.0`). Parameters missing from a file take
the default file's values (`DEFAULT_PATH`, the spec section 10 table). Damping is either explicit
(`damping_u`, `damping_theta`) or a `damping_ratio` from which both are derived per lattice kind
(spec 6.3, as `Material.paper` does); an explicit coefficient wins over the ratio.
"""

import datetime
import json
import math
import os
import tempfile
import tomllib
from pathlib import Path

from design_engine.physics.lattice import Lattice
from design_engine.physics.material import DEFAULT_FILE, Material, default_si

FORMAT = "metarig-material/1"
DEFAULT_PATH = DEFAULT_FILE

SI_UNITS: dict[str, str] = {
    "k_stretch": "N/m",
    "k_shear": "N/m",
    "k_bend": "N m/rad",
    "k_contact": "N m/rad",
    "contact_min_deg": "deg",
    "contact_cutoff_deg": "deg",
    "density": "kg/m^2",
    "damping_u": "N s/m",
    "damping_theta": "N m s",
    "damping_ratio": "1",
}

DESCRIPTIONS = {
    "k_stretch": "ligament axial (stretch) stiffness k_l",
    "k_shear": "ligament shear stiffness k_s",
    "k_bend": "ligament bending stiffness k_theta",
    "k_contact": "contact stiffness k_c",
    "contact_min_deg": "contact asymptote angle theta_min",
    "contact_cutoff_deg": "contact onset angle theta_cutoff",
    "density": "areal density rho of the units",
    "damping_u": "translational damping c_u = c_v",
    "damping_theta": "rotational damping c_theta",
    "damping_ratio": "damping ratio zeta (derives c_u, c_theta per lattice, spec 6.3)",
}

_POSITIVE = ("k_stretch", "k_shear", "k_bend", "density")
_NONNEGATIVE = ("k_contact", "damping_u", "damping_theta", "damping_ratio")
_TOP_KEYS = ("format", "source", "created", "notes", "parameters")
_PARAM_KEYS = ("value", "stderr", "unit", "description")


class MaterialFileError(ValueError):
    """A bad material file or value; the message is one line naming the file and/or the key."""


class MaterialValues(dict):
    """SI values that a material source gives explicitly (no defaults merged), validated once:
    known keys, finite numbers, signs, the contact angles' order, and complete once merged with
    the default file's values. Made only by `MaterialValues.checked` (which `read_material_file`
    and `material_for_scene` call where the values come in); everything downstream takes it as
    it is. Read-only."""

    @classmethod
    def checked(cls, values: dict[str, float]) -> "MaterialValues":
        """Validated values (a `MaterialValues` is returned as it is); raises
        `MaterialFileError` naming the key."""
        if isinstance(values, MaterialValues):
            return values
        given = check_values(values)
        merged = default_si()
        merged.update(given)
        check_values(merged, complete=True)
        return cls._of_checked(given)

    @classmethod
    def _of_checked(cls, values: dict[str, float]) -> "MaterialValues":
        out = cls()
        dict.update(out, values)
        return out

    def __reduce__(self):  # copies and pickles (Dask) hold values that were validated already
        return (MaterialValues._of_checked, (dict(self),))

    def _read_only(self, *args, **kwargs):
        raise TypeError("MaterialValues are read-only: make new ones with MaterialValues.checked")

    __setitem__ = __delitem__ = update = pop = popitem = clear = setdefault = _read_only


def _number(key: str, x, what: str = "value") -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise MaterialFileError(f"{key}: {what} must be a number, got {x!r}")
    x = float(x)
    if not math.isfinite(x):
        raise MaterialFileError(f"{key}: {what} must be finite, got {x}")
    return x


def check_values(values: dict[str, float], *, complete: bool = False) -> dict[str, float]:
    """Validated copy of SI values: known keys, finite numbers, signs, contact angle order.

    With `complete`, every stiffness, angle and the density must be present, and damping given
    as both coefficients or a ratio. Raises `MaterialFileError` naming the key.
    """
    out = {}
    for k, x in values.items():
        if k not in SI_UNITS:
            raise MaterialFileError(f"{k}: unknown material parameter (known: {', '.join(SI_UNITS)})")
        x = _number(k, x)
        if k in _POSITIVE and not x > 0:
            raise MaterialFileError(f"{k}: must be > 0 {SI_UNITS[k]}, got {x}")
        if k in _NONNEGATIVE and not x >= 0:
            raise MaterialFileError(f"{k}: must be >= 0 {SI_UNITS[k]}, got {x}")
        out[k] = x
    lo, hi = out.get("contact_min_deg"), out.get("contact_cutoff_deg")
    if lo is not None and not -90.0 < lo < 0.0:
        raise MaterialFileError(f"contact_min_deg: must lie in (-90, 0) deg, got {lo}")
    if hi is not None and not -90.0 < hi <= 0.0:
        raise MaterialFileError(f"contact_cutoff_deg: must lie in (-90, 0] deg, got {hi}")
    if lo is not None and hi is not None and not lo < hi:
        raise MaterialFileError(f"contact_min_deg: must be below contact_cutoff_deg, got {lo} >= {hi} deg")
    if complete:
        for k in ("k_stretch", "k_shear", "k_bend", "k_contact", "contact_min_deg",
                  "contact_cutoff_deg", "density"):
            if k not in out:
                raise MaterialFileError(f"{k}: missing")
        if "damping_ratio" not in out and not ("damping_u" in out and "damping_theta" in out):
            k = "damping_u" if "damping_u" not in out else "damping_theta"
            raise MaterialFileError(f"{k}: missing (give damping_u and damping_theta, or damping_ratio)")
    return out


def material_to_si(m: Material) -> dict[str, float]:
    """SI values of a material (explicit damping, no ratio): N/m, N m/rad, deg, kg/m^2, N s/m, N m s."""
    return m.to_si()


def material_from_si(values: dict[str, float], lattice: Lattice | None = None) -> Material:
    """Engine `Material` from SI values; missing keys take the default file's values.

    `lattice` is needed only when damping comes from `damping_ratio` (then it is derived for
    that lattice kind). Raises `MaterialFileError` (one line naming the key) on bad values.
    """
    given = MaterialValues.checked(values)
    merged = default_si()  # an explicit damping coefficient wins over the (default) ratio
    merged.update(given)
    needs_ratio = "damping_u" not in merged or "damping_theta" not in merged
    if needs_ratio and lattice is None:
        raise MaterialFileError("damping_ratio: deriving damping from the ratio needs a lattice")
    try:
        return Material.from_si(merged, lattice)
    except (ValueError, TypeError) as e:
        raise MaterialFileError(str(e).splitlines()[0]) from None


def _read(path: Path) -> dict:
    try:
        if path.suffix.lower() == ".json":
            doc = json.loads(path.read_text())
        else:
            with path.open("rb") as f:
                doc = tomllib.load(f)
    except FileNotFoundError:
        raise MaterialFileError(f"{path}: no such material file") from None
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise MaterialFileError(f"{path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'TOML'}: "
                                f"{str(e).splitlines()[0]}") from None
    except OSError as e:
        raise MaterialFileError(f"{path}: cannot read: {e.strerror or e}") from None
    if not isinstance(doc, dict):
        raise MaterialFileError(f"{path}: the document must be a table")
    return doc


def read_material_file(path) -> tuple[dict[str, float], dict[str, float]]:
    """(values, stderrs) given explicitly in a material file, SI; no defaults merged. The values
    are validated here, once (`MaterialValues`).

    Raises `MaterialFileError` (one line naming the file and the key) on a malformed file, wrong
    format, unknown key, wrong unit or bad value.
    """
    path = Path(path)
    doc = _read(path)
    fmt = doc.get("format")
    if fmt != FORMAT:
        raise MaterialFileError(f"{path}: format: expected {FORMAT!r}, got {fmt!r}")
    for k in doc:
        if k not in _TOP_KEYS:
            raise MaterialFileError(f"{path}: {k}: unknown key (known: {', '.join(_TOP_KEYS)})")
    params = doc.get("parameters", {})
    if not isinstance(params, dict):
        raise MaterialFileError(f"{path}: parameters: must be a table")
    if not params:  # the parameters come after the header: a cut-short file keeps only that
        raise MaterialFileError(f"{path}: sets no parameter (no [parameters]; an empty or "
                                "cut-short file?)")
    values, stderr = {}, {}
    try:
        for k, p in params.items():
            if k not in SI_UNITS:
                raise MaterialFileError(f"{k}: unknown material parameter (known: {', '.join(SI_UNITS)})")
            if not isinstance(p, dict):
                p = {"value": p}
            for kk in p:
                if kk not in _PARAM_KEYS:
                    raise MaterialFileError(f"{k}.{kk}: unknown key (known: {', '.join(_PARAM_KEYS)})")
            if "value" not in p:
                raise MaterialFileError(f"{k}: no value")
            if "unit" in p and p["unit"] != SI_UNITS[k]:
                raise MaterialFileError(f"{k}: unit must be {SI_UNITS[k]!r} (SI), got {p['unit']!r}")
            values[k] = _number(k, p["value"])
            if "stderr" in p:
                s = _number(k, p["stderr"], "stderr")
                if s < 0:
                    raise MaterialFileError(f"{k}: stderr must be >= 0, got {s}")
                stderr[k] = s
        values = MaterialValues.checked(values)
    except MaterialFileError as e:
        raise MaterialFileError(f"{path}: {e}") from None
    return values, stderr


def load_material_file(path) -> tuple[dict[str, float], dict[str, float]]:
    """(values, stderrs) of a material file, SI; missing parameters take the default file's values.

    A default value comes without a stderr. Errors as `read_material_file`.
    """
    values, stderr = read_material_file(path)
    merged = default_si()
    merged.update(values)
    return merged, stderr


def load_material(path, lattice: Lattice | None = None) -> Material:
    """Engine `Material` (internal units) of a material file; `lattice` for ratio damping."""
    values, _ = load_material_file(path)
    try:
        return material_from_si(values, lattice)
    except MaterialFileError as e:
        raise MaterialFileError(f"{Path(path)}: {e}") from None


def default_material(lattice: Lattice) -> Material:
    """The default material file's material for `lattice` (equal to `Material.paper(lattice)`)."""
    return load_material(DEFAULT_PATH, lattice)


def _toml_str(s: str) -> str:
    return json.dumps(str(s), ensure_ascii=False)  # a JSON string is a valid TOML basic string


def _toml_float(x: float) -> str:
    r = repr(float(x))
    return r if any(c in r for c in ".eE") else r + ".0"


def material_toml(values_si: dict[str, float], stderr_si: dict[str, float] | None = None,
                  source: str = "", notes: str = "", created: str | None = None) -> str:
    """TOML text of a material file (see the module docstring); values validated first."""
    values = check_values(values_si)
    stderr = dict(stderr_si or {})
    for k, s in stderr.items():
        if k not in values:
            raise MaterialFileError(f"{k}: stderr given without a value")
        if _number(k, s, "stderr") < 0:
            raise MaterialFileError(f"{k}: stderr must be >= 0, got {s}")
    if created is None:
        created = datetime.datetime.now(datetime.UTC).replace(microsecond=0).isoformat()
        created = created.replace("+00:00", "Z")
    lines = [
        f"# metarig material file ({FORMAT}), SI units; see README 'Material files'.",
        f"format = {_toml_str(FORMAT)}",
        f"source = {_toml_str(source)}",
        f"created = {_toml_str(created)}",
        f"notes = {_toml_str(notes)}",
    ]
    for k, unit in SI_UNITS.items():
        if k not in values:
            continue
        lines += ["", f"[parameters.{k}]  # {DESCRIPTIONS[k]}", f"value = {_toml_float(values[k])}"]
        if k in stderr:
            lines.append(f"stderr = {_toml_float(stderr[k])}")
        lines.append(f"unit = {_toml_str(unit)}")
    return "\n".join(lines) + "\n"


def save_material(path, values_si: dict[str, float], stderr_si: dict[str, float] | None = None,
                  source: str = "", notes: str = "") -> Path:
    """Write a material file (TOML, SI) atomically; returns the path.

    `values_si` maps names of `SI_UNITS` to SI values (a subset is fine: the rest is the default
    on loading); `stderr_si` the standard errors of some of them.
    """
    path = Path(path)
    text = material_toml(values_si, stderr_si, source, notes)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def material_for_scene(scene, source) -> tuple[Material, dict[str, float]]:
    """(material, explicit SI values) of `source` for `scene`'s lattice.

    `source` is a material file path or a dict of SI values (as recorded in a design document
    under `material_si`). Missing parameters take the default file's values, except the contact
    angles: when the source sets neither, the scene's own (preset or task) angles are kept.
    """
    if isinstance(source, dict):
        try:
            given = MaterialValues.checked(source)
        except MaterialFileError as e:
            raise MaterialFileError(f"material: {e}") from None
        where = "material"
    else:
        given, _ = read_material_file(source)
        where = str(source)
    cur = scene.material
    has_min, has_cut = "contact_min_deg" in given, "contact_cutoff_deg" in given
    values = given
    try:
        if has_min != has_cut:  # one angle given: the other is the scene's (a new combination)
            other = "contact_cutoff_deg" if has_min else "contact_min_deg"
            values = MaterialValues.checked({**given, other: math.degrees(
                cur.contact_cutoff if has_min else cur.contact_min)})
        m = material_from_si(values, scene.lattice)
    except MaterialFileError as e:
        raise MaterialFileError(f"{where}: {e}") from None
    if not (has_min or has_cut):
        import equinox as eqx

        m = eqx.tree_at(lambda x: (x.contact_min, x.contact_cutoff), m,
                        (cur.contact_min, cur.contact_cutoff))
    return m, given


def with_material(scene, source):
    """`scene` with its material replaced by that of `source` (path or SI dict, see
    `material_for_scene`)."""
    import dataclasses

    return dataclasses.replace(scene, material=material_for_scene(scene, source)[0])
