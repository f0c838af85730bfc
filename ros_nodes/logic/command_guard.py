"""Who may command motion: the allow-list check of the shaker's and the stage's motion services
(pure: no rclpy).

A motion request (`/shaker/fire`, `/stage/set_strain`) is accepted only while every node that
has a client on that service is on the node's allow-list (`allowed_callers`, fully qualified
node names; default the experiment's sequencer, `/sequencer`; `*` lets any node in). rclpy
hands a service callback the request without its sender (the Python request id carries only
a sequence number, not the client's GUID), so the caller of one request cannot be told apart
from the other clients of the service: while a node not on the list has a client there, every
motion request is refused, with that node's name as the reason (fail closed). A client whose
node the graph does not know yet (discovery still under way) counts as not on the list.
Stopping is never guarded: `/shaker/stop`, `/stage/stop` and `/rig/stop` take anyone.

Names are DDS participants' own claims, not authenticated: this keeps other programs and
people's scripts on the same domain from moving the rig by mistake; keeping a hostile
participant out is DDS security's job (SROS2), with discovery on this machine by default.
"""

ANYONE = "*"
UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"  # rmw's name of a node not (yet) known to the graph


def full_name(namespace: str, name: str) -> str:
    """The fully qualified node name: `/ns/name` (`/name` in the root namespace)."""
    if name == UNKNOWN_NODE or namespace.startswith("_NODE_NAMESPACE_UNKNOWN"):
        return UNKNOWN_NODE
    return "/" + "/".join(p for p in (*namespace.split("/"), *name.split("/")) if p)


def normalised(names) -> tuple[str, ...]:
    """Allow-list entries as fully qualified names (a leading `/` added; `*` kept)."""
    return tuple(n if n == ANYONE else full_name("/", n.strip()) for n in names if n.strip())


def request_topic(service: str) -> str:
    """The DDS topic a service's clients write their requests on (rmw_fastrtps and
    rmw_cyclonedds name it `rq<service>Request`)."""
    return f"rq{service}Request"


def refusal(service: str, clients: list[str], allowed: tuple[str, ...]) -> str | None:
    """Why a motion request on `service` is refused, or None to accept it.

    Args:
        service: the service's name, e.g. "/shaker/fire".
        clients: fully qualified names of the nodes with a client on it (one per client
            endpoint; `UNKNOWN_NODE` for one the graph cannot name yet).
        allowed: the allow-list (`normalised`); `*` accepts any caller.
    """
    allowed = normalised(allowed)
    if ANYONE in allowed:
        return None
    listed = ", ".join(allowed) or "nobody"
    if not clients:
        return (f"no client of {service} is known yet (discovery under way): the caller cannot "
                f"be checked against the allow-list ({listed}); try again")
    others = sorted({c for c in clients if c not in allowed})
    if not others:
        return None
    named = [c for c in others if c != UNKNOWN_NODE]
    who = ", ".join(named) + (" and " if named and len(named) < len(others) else "") + \
        ("a node not known yet (discovery under way)" if UNKNOWN_NODE in others else "")
    return (f"{who} may not command motion (allowed_callers: {listed}); while a node not on "
            f"the list has a client on {service}, no motion request there is accepted (a "
            "request does not say which client sent it)")
