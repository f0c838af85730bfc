"""ROS 2 message definitions as text, for MCAP schemas (rosbag2 `ros2msg` style).

A schema is the message's own `.msg` text, then every type it uses (recursively), each after a
line of 80 `=` and `MSG: pkg/Type`. Definitions come from `<prefix>/share/<pkg>/msg/*.msg`,
where the ROS wheels and `ros_nodes.interfaces.build` install them. Pure: no rclpy.
"""

import re
import sys
from functools import lru_cache
from pathlib import Path

SEPARATOR = "=" * 80
PRIMITIVES = frozenset({"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16",
                        "uint16", "int32", "uint32", "int64", "uint64", "string", "wstring"})


class UnknownMessageType(LookupError):
    """No `.msg` file was found for a type name."""


def normalize(type_name: str) -> tuple[str, str]:
    """`pkg/msg/Type` or `pkg/Type` -> (pkg, Type)."""
    parts = type_name.strip("/").split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise UnknownMessageType(f"not a message type name: {type_name!r}")


def share_dirs() -> list[Path]:
    return [Path(sys.prefix) / "share"]


@lru_cache(maxsize=None)
def msg_text(pkg: str, name: str) -> str:
    """The raw `.msg` text of pkg/Type."""
    for share in share_dirs():
        p = share / pkg / "msg" / f"{name}.msg"
        if p.exists():
            return p.read_text()
    raise UnknownMessageType(f"no definition for {pkg}/msg/{name} under {share_dirs()}")


def _field_types(pkg: str, text: str) -> list[tuple[str, str]]:
    """The non-primitive field types of a definition, as (pkg, Type), in order of appearance."""
    out = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        # strip array and bounded-string suffixes: float64[] x, uint8[16] y, string<=8 z
        ftype = re.sub(r"\[.*\]$", "", line.split()[0])
        ftype = re.sub(r"<=\d+$", "", ftype)
        if ftype in PRIMITIVES:
            continue
        if ftype == "Header":
            out.append(("std_msgs", "Header"))
        elif "/" in ftype:
            p, t = ftype.split("/")[0], ftype.split("/")[-1]
            out.append((p, t))
        else:
            out.append((pkg, ftype))
    return out


@lru_cache(maxsize=None)
def schema_text(type_name: str) -> str:
    """The full rosbag2-style definition of a message type (with all dependencies)."""
    pkg, name = normalize(type_name)
    main = msg_text(pkg, name)
    seen: list[tuple[str, str]] = []
    stack = list(reversed(_field_types(pkg, main)))
    while stack:
        dep = stack.pop()
        if dep in seen:
            continue
        seen.append(dep)
        stack.extend(reversed(_field_types(dep[0], msg_text(*dep))))
    parts = [main.rstrip("\n")]
    for p, t in seen:
        parts.append(f"{SEPARATOR}\nMSG: {p}/{t}\n{msg_text(p, t).rstrip(chr(10))}")
    return "\n".join(parts) + "\n"


def has_header(type_name: str) -> bool:
    """True when the first field of the message is a `std_msgs/Header` (stamp at CDR offset 4)."""
    pkg, name = normalize(type_name)
    for line in msg_text(pkg, name).splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            return line.split()[0] in ("std_msgs/Header", "Header")
    return False
