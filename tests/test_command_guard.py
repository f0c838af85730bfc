"""Who may command motion (`ros_nodes.logic.command_guard`), without ROS: the allow-list
against the nodes that have a client on a motion service."""

from ros_nodes.logic.command_guard import UNKNOWN_NODE, full_name, normalised, refusal, \
    request_topic

SEQ = ("/sequencer",)


def test_names_are_fully_qualified():
    assert full_name("/", "sequencer") == "/sequencer"
    assert full_name("/lab/ui", "gui") == "/lab/ui/gui"
    assert full_name("_NODE_NAMESPACE_UNKNOWN_", UNKNOWN_NODE) == UNKNOWN_NODE
    assert normalised(["sequencer", " /lab/gui ", "*", ""]) == ("/sequencer", "/lab/gui", "*")
    assert request_topic("/shaker/fire") == "rq/shaker/fireRequest"


def test_only_listed_clients_may_command():
    assert refusal("/shaker/fire", ["/sequencer"], SEQ) is None
    assert refusal("/shaker/fire", ["/sequencer", "/sequencer"], ["sequencer"]) is None
    why = refusal("/shaker/fire", ["/sequencer", "/elsewhere/script"], SEQ)
    assert why.startswith("/elsewhere/script may not command motion (allowed_callers: "
                          "/sequencer); while a node not on the list has a client on "
                          "/shaker/fire, no motion request there is accepted")
    assert refusal("/shaker/fire", ["/elsewhere/script"], ["/sequencer", "/elsewhere/script"]) \
        is None
    assert refusal("/shaker/fire", ["/anything"], ["*"]) is None


def test_a_caller_that_cannot_be_named_is_refused():
    why = refusal("/stage/set_strain", ["/sequencer", UNKNOWN_NODE], SEQ)
    assert why.startswith("a node not known yet (discovery under way) may not command motion")
    why = refusal("/stage/set_strain", ["/b", UNKNOWN_NODE, "/a"], SEQ)
    assert why.startswith("/a, /b and a node not known yet (discovery under way) may not")
    assert refusal("/stage/set_strain", [], SEQ).startswith(
        "no client of /stage/set_strain is known yet (discovery under way)")
    assert "allowed_callers: nobody" in refusal("/stage/set_strain", ["/a"], ())
