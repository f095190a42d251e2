"""The parts the ROS nodes are made of, each on its own: built from plain objects, a fake clock, a
fake Health and logger, without a node."""

from __future__ import annotations

from collections import Counter
from types import SimpleNamespace

import pytest
import torch
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus
from medc_agents.team_state import TeamObserver
from medc_sim import messages

OK, WARN = DiagnosticStatus.OK, DiagnosticStatus.WARN
IDS = ["agent_0", "agent_1", "agent_2"]


class _Clock:
    """A clock that moves only when told."""

    def __init__(self, now: float = 100.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class _Health:
    """The conditions set and the events sent, as a node's Health keeps and logs them."""

    def __init__(self) -> None:
        self.states: dict[str, tuple[bytes, str]] = {}
        self.sets: list[tuple[str, bytes, str]] = []
        self.events: list[tuple[str, bytes, str]] = []

    def set(self, part: str, level: bytes, message: str, values=None, log: bool = True) -> None:
        self.states[part] = (level, message)
        self.sets.append((part, level, message))

    def level(self, part: str) -> bytes:
        return self.states.get(part, (OK, ""))[0]

    def event(self, part: str, level: bytes, message: str, values=None) -> None:
        self.events.append((part, level, message))


class _Log:
    """A logger that keeps its lines by level."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def __getattr__(self, level: str):
        return lambda text: self.lines.append((level, text))

    def said(self, level: str) -> list[str]:
        return [text for lvl, text in self.lines if lvl == level]


def _waiting_observer() -> TeamObserver:
    """An observer whose step 0 of episode 1 waits: its map and status are here, no pose or reading."""
    o = TeamObserver("agent_0", 3, 10)
    o.add_map(messages.grid_msg(torch.zeros((10, 10), dtype=torch.bool), Time(sec=1), 1.0))
    o.add_status(messages.status_msg(IDS, 1, 0, Time(sec=10), Time(sec=1)))
    return o


# ---------------------------------------------------------------- the agent node's parts
def test_a_stall_is_reported_once_after_the_timeout_and_over_when_its_step_is_decided():
    from medc_agents.team_watch import StallWatch

    o, health, clock = _waiting_observer(), _Health(), _Clock()
    policy = [False]
    stalls = StallWatch(o, health, 2.0, lambda: policy[0], clock)
    stalls.check()  # the step is seen waiting: the wait starts now
    clock.now += 1.9
    stalls.check()
    assert stalls.reported == 0 and "team step" not in health.states
    clock.now += 0.2
    stalls.check()
    level, report = health.states["team step"]
    assert level == WARN and stalls.reported == 1
    assert report.startswith("stalled: episode 1 step 0 (stamp 10.000000000) not decided after 2.1 s; ")
    assert "waiting for: " in report and report.split("; have: ")[0].endswith("; a policy")
    clock.now += 5.0
    stalls.check()  # the same stall: reported once
    assert stalls.reported == 1 and len(health.sets) == 1
    stalls.over(o.clock.open_tick())
    assert health.states["team step"] == (OK, "deciding again: episode 1 step 0 decided")


def test_another_sender_on_the_own_move_topic_warns_until_clear_s_without_one():
    from medc_agents.team_watch import CLEAR_S, ClaimWatch

    health, clock = _Health(), _Clock()
    claims = ClaimWatch("agent_1", "own", health, clock)
    claims.on_move(SimpleNamespace(sender="own"))  # this node's own move
    claims.check()
    assert health.sets == []
    claims.on_move(SimpleNamespace(sender="other"))
    level, message = health.states["moves"]
    assert level == WARN and message.startswith("another process publishes moves as agent_1 (sender 'other'; "
                                                "this node is own)")
    clock.now += CLEAR_S - 0.5
    claims.check()
    assert health.level("moves") == WARN
    clock.now += 0.5
    claims.check()
    assert health.states["moves"] == (OK, f"no other process has moved as agent_1 for {CLEAR_S:g} s")


def test_old_statuses_are_summed_up_in_one_line_per_period():
    from medc_agents.team_watch import OldStatuses

    log, clock, dropped = _Log(), _Clock(), Counter()
    old = OldStatuses(log, dropped, 10.0, clock)
    old.sum_up()  # nothing dropped: the period starts now
    for _ in range(3):
        old.drop("re-sent step 4")
    clock.now += 4.0
    old.sum_up()
    assert log.said("info") == [] and len(log.said("debug")) == 3
    clock.now += 6.0
    old.sum_up()
    assert log.said("info") == ["3 statuses below the step answered dropped in the last 10 s (a driver's "
                                "re-sends that crossed its next step: normal; 3 in all)"]
    assert dropped["old status"] == 3 and old.count == 0


class _Slot:
    """A policy slot that takes paths ending in .safetensors and refuses anything else."""

    observation = "maps"

    def __init__(self) -> None:
        self.current = None

    def swap(self, source: str):
        from medc_agents.policy_slot import PolicyRejected

        if not source.endswith(".safetensors"):
            raise PolicyRejected(f"{source} is no bundle")
        self.current = SimpleNamespace(description=f"bundle {source}")
        return self.current

    def runs_in(self) -> str:
        return ""  # no network: the log line names no runtime


def _swaps(fetched: list[str], ready: bool = True):
    from medc_agents.policy_slot import PolicyRejected
    from medc_agents.policy_swaps import PolicySwaps

    def fetch(cid: str) -> None:
        if not ready:
            raise PolicyRejected("registry bridge service /medc/registry/fetch_bundle is not running")
        fetched.append(cid)

    observer = SimpleNamespace(observation=None)
    observer.use_observation = lambda spec: setattr(observer, "observation", SimpleNamespace(name=spec))
    log, dropped = _Log(), Counter()
    return PolicySwaps(_Slot(), observer, log, dropped, fetch), log, dropped


def test_policy_swaps_take_a_bundle_refuse_anything_else_and_pass_content_ids_to_the_fetch():
    from std_msgs.msg import String

    fetched: list[str] = []
    swaps, log, dropped = _swaps(fetched)
    heard: list = []
    swaps.listeners.append(lambda source, why: heard.append((source, why)))
    swaps.on_message(String(data=" team.safetensors "))
    assert log.said("info") == ["now running policy bundle team.safetensors (observation maps)"]
    swaps.on_message(String(data="notes.txt"))
    assert log.said("error") == ["policy 'notes.txt' refused, keeping the running one: "
                                 "notes.txt is no bundle"]
    assert swaps.slot.current.description == "bundle team.safetensors" and dropped["policy"] == 1
    assert heard == [("team.safetensors", None), ("notes.txt", "notes.txt is no bundle")]
    cid = "bafkreigh2akiscaildcqabsyg3dfr6chu3fgpregiymsck7e7aqa4s52zy"
    swaps.on_message(String(data=cid))
    assert fetched == [cid] and dropped["policy"] == 1
    param = SimpleNamespace(name="policy", value="x.onnx")
    result = swaps.on_set_parameters([param])
    assert not result.successful and result.reason == "x.onnx is no bundle"
    assert swaps.on_set_parameters([SimpleNamespace(name="policy", value="b.safetensors")]).successful


def test_a_content_id_the_bridge_cannot_fetch_is_a_refused_policy_message():
    from std_msgs.msg import String

    swaps, log, dropped = _swaps([], ready=False)
    cid = "bafkreigh2akiscaildcqabsyg3dfr6chu3fgpregiymsck7e7aqa4s52zy"
    swaps.on_message(String(data=cid))
    assert dropped["policy"] == 1 and swaps.slot.current is None
    assert log.said("error") == [f"policy {cid!r} refused, keeping the running one: registry bridge service "
                                 "/medc/registry/fetch_bundle is not running"]


def test_a_hot_swap_to_a_bundle_from_another_world_is_refused_in_one_line_unless_allowed(bundles):
    """Swapping (a parameter set, a policy message) to a bundle trained in another world keeps the
    running policy and logs one line naming the world; an agent started with allow_other_world takes
    it, and refuses it at start without."""
    from medc_agents.policy_slot import PolicyRejected, PolicySlot
    from medc_agents.policy_swaps import PolicySwaps
    from std_msgs.msg import String

    grid, other = str(bundles["a"]), str(bundles["radbench"])

    def swaps(allow: bool) -> tuple[PolicySwaps, _Log]:
        observer = SimpleNamespace(observation=None)
        observer.use_observation = lambda spec: setattr(observer, "observation", SimpleNamespace(name=spec))
        log = _Log()
        slot = PolicySlot((5, 10, 10), 8, grid=10, allow_other_world=allow)
        return PolicySwaps(slot, observer, log, Counter(), lambda cid: None), log

    refusing, log = swaps(False)
    refusing.start(grid)
    result = refusing.on_set_parameters([SimpleNamespace(name="policy", value=other)])
    assert not result.successful and "trained in the 'radbench' world" in result.reason
    refusing.on_message(String(data=other))
    errors = log.said("error")
    assert len(errors) == 2 and all(e.startswith(f"policy '{other}' refused, keeping the running one: "
                                                 f"policy bundle '{other}' was trained in the 'radbench' "
                                                 "world with transmission_max=0.3") for e in errors)
    assert refusing.slot.current.source == grid
    with pytest.raises(PolicyRejected, match=r"refused, not starting: .*allow_other_world true"):
        swaps(False)[0].start(other)
    allowing, log = swaps(True)
    allowing.start(grid)
    assert allowing.on_set_parameters([SimpleNamespace(name="policy", value=other)]).successful
    assert allowing.slot.current.source == other and log.said("error") == []


def test_moves_out_publish_each_decision_and_answer_a_resent_step_once_more():
    from medc_agents.node import MoveOut
    from medc_agents.team_episode import Tick

    sent: list = []
    moves = MoveOut("agent_2", "me", sent.append, lambda: Time(sec=7))
    t0, t1 = Tick(1, 0, 10, 1), Tick(1, 1, 11, 1)
    moves.publish(t0, 3)
    assert [(m.agent_id, m.sender, m.episode, m.step, m.action) for m in sent] == [("agent_2", "me", 1, 0, 3)]
    assert sent[0].header.stamp.sec == 7 and moves.count == 1
    assert moves.again(t0) is None and len(sent) == 2 and sent[1] is sent[0]  # the same move again
    moves.unanswered = ("obs", "mask", t1)  # the policy failed on step 1
    assert moves.again(t1) == ("obs", "mask", t1) and len(sent) == 2
    moves.publish(t1, 5)
    assert moves.unanswered is None and moves.count == 2


@pytest.mark.parametrize(("verdict", "admitted", "level", "counted"),
                         [("take", True, OK, None), ("hold", False, WARN, "held status"),
                          ("drop", False, OK, "old"), ("restart", True, OK, "restart")])
def test_status_intake_follows_the_gates_verdict(verdict, admitted, level, counted):
    from medc_agents.team_watch import StatusIntake

    health, dropped, old, restarts = _Health(), Counter(), [], []
    gate = SimpleNamespace(admit=lambda *a: (verdict, "why" if verdict != "take" else ""))
    intake = StatusIntake(gate, health, dropped, old.append, lambda: restarts.append(1))
    msg = messages.status_msg(IDS, 1, 0, Time(sec=10), Time(sec=1))
    clock = SimpleNamespace(episode=1, map=1, step=-1)
    assert intake.admit(msg, clock) is admitted
    assert health.level("status") == level
    assert (dropped["held status"] == 1) is (counted == "held status")
    assert (old == ["why"]) is (counted == "old")
    assert (restarts == [1] and health.events == [("status", WARN, "why")]) is (counted == "restart")


# ---------------------------------------------------------------- the simulator node's parts
def test_a_move_fault_is_logged_once_per_period_its_repeats_summed_up_then_ok():
    from medc_sim.move_watch import MoveFaults

    health, log, clock, timers = _Health(), _Log(), _Clock(), []
    faults = MoveFaults(health, log, lambda period, tick: timers.append((period, tick)), clock, repeat_s=10.0)
    assert timers == []  # no timer before the first fault
    faults.report("conflict agent_0", "conflicting moves: first")
    for n in range(3):
        clock.now += 1.0
        faults.report("conflict agent_0", f"conflicting moves: again {n}")
    assert [period for period, _ in timers] == [1.0]
    assert health.states["moves"] == (WARN, "conflicting moves: again 2")
    clock.now += 7.0
    faults.tick()  # 10 s after the first: the repeats summed up in one line
    assert log.said("warning") == ["conflict agent_0: 3 more in the last 10 s (logged once per period; "
                                   "the latest on /diagnostics)"]
    assert health.level("moves") == WARN  # the last fault came 7 s ago
    clock.now += 3.0
    faults.tick()
    assert health.states["moves"] == (OK, "no duplicate or conflicting move for 10 s")



def test_a_refused_move_is_reported_by_its_kind_and_a_conflicting_one_is_not_dropped():
    from medc_sim.move_watch import MoveFaults
    from medc_sim.moves import MoveBook, MoveRejected

    health, log = _Health(), _Log()
    faults = MoveFaults(health, log, lambda period, tick: None, _Clock())
    book = MoveBook(3, 8)
    book.open(0, 0)
    book.offer("agent_1", 0, 0, 2, "me")
    dropped = {}
    offers = (("conflict", ("agent_1", 0, 0, 3, "me")), ("duplicate", ("agent_1", 0, 0, 2, "other")))
    for kind, offer in offers:
        try:
            book.offer(*offer)
        except MoveRejected as exc:
            dropped[kind] = faults.refused("agent_1", exc)
            assert health.states["moves"][0] == WARN and kind in health.states["moves"][1]
    assert dropped == {"conflict": False, "duplicate": True}
    assert faults.refused("agent_1", MoveRejected("a move of another graph")) is True
    assert log.said("warning") == ["dropped move: a move of another graph"]
    assert health.states["moves"] == (WARN, "foreign move: a move of another graph")

def _step_watch(**kw):
    from medc_sim.move_watch import StepWatch
    from medc_sim.moves import MoveBook

    book = MoveBook(3, 8)
    book.open(0, 0)
    calls: list[str] = []
    clock, perf = _Clock(), _Clock(0.0)
    args = dict(send=lambda: calls.append("send"), advance=lambda: calls.append("advance"),
                running=lambda: True, resend_s=0.5, stall_timeout_s=2.0, move_timeout_s=3.0, rate_hz=0.0)
    args.update(kw)
    steps = StepWatch(book, IDS, _Health(), _Log(), clock=clock, perf=perf, **args)
    steps.opened()
    steps.sent()
    return steps, book, calls, clock, perf


def test_a_step_without_moves_is_resent_every_resend_s_and_its_stall_reported_once():
    steps, book, calls, clock, perf = _step_watch()
    clock.now += 0.4
    steps.resend_tick()
    assert calls == [] and steps.resends == 0
    for _ in range(5):  # every 0.5 s, the step re-sent (sent() as the node's send does)
        clock.now += 0.5
        perf.now += 0.5
        steps.resend_tick()
        steps.sent()
    assert calls == ["send"] * 5 and steps.resends == 5
    stalls = [s for s in steps.health.sets if s[0] == "team step"]
    assert len(stalls) == 1 and stalls[0][1] == WARN
    assert stalls[0][2].startswith("episode 0 step 0: no move from agent_0, agent_1, agent_2 after 2.0 s; "
                                   "re-sending the step every 0.5 s")
    book.open(0, 1)
    steps.opened()  # the next step: the stall is over
    assert steps.health.states["team step"] == (OK, "stepping again")


def test_an_agent_without_a_move_is_taken_out_after_move_timeout_s_and_the_step_goes_on():
    steps, book, calls, _, perf = _step_watch()
    for agent in ("agent_0", "agent_1"):
        book.offer(agent, 0, 0, 1, "s-" + agent)
        steps.took()
    book.known[2] = True  # agent_2 has moved before: no start-up grace
    perf.now += 2.9
    steps.move_timeout_tick()
    assert calls == [] and not book.lost
    perf.now += 0.2
    steps.move_timeout_tick()
    assert book.lost == {2} and calls == ["advance"] and steps.latency() is None
    level, message = steps.health.states["team"]
    assert level == WARN and message.startswith("agent_2 lost: no move within move_timeout_s (3 s)")


def test_the_start_gate_counts_its_endpoints_matches_and_expires_after_its_timeout():
    from medc_sim.start_gate import StartGate

    def endpoint(subscriptions: int = 0, publishers: int = 0):
        return SimpleNamespace(get_subscription_count=lambda: subscriptions,
                               get_publisher_count=lambda: publishers)

    clock = _Clock()
    status = endpoint(subscriptions=3)  # the simulator's own watch and two agents
    moves = [endpoint(publishers=1), endpoint(publishers=1), endpoint()]
    gate = StartGate(status, moves, endpoint(subscriptions=0), 3, 1, timeout_s=30.0, clock=clock)
    assert gate.missing() == ["2 of 3 expected status subscribers", "2 of 3 agents' move publishers",
                              "0 of 1 expected episode-result readers"]
    ready = StartGate(endpoint(subscriptions=4), [endpoint(publishers=1)] * 3, endpoint(subscriptions=1),
                      3, 1, clock=clock)
    assert ready.missing() == []
    assert not gate.expired()
    clock.now += 30.5
    assert gate.expired()
    with pytest.raises(ValueError, match="must be >= 0"):
        StartGate(status, moves, endpoint(), -1, 0)


def test_the_graph_watch_reports_another_driver_and_a_foreign_map_then_ok_again():
    from medc_sim.watch import CLEAR_S, REPUBLISH_DELAY_S, GraphWatch

    made: list = []
    node = SimpleNamespace(create_subscription=lambda *a: made.append(a[1]),
                           create_timer=lambda period, tick: made.append((period, tick)))
    health, clock, republished = _Health(), _Clock(), []
    watch = GraphWatch(node, None, "/medc", "mine", health, started=lambda: True, finished=lambda: False,
                       republish=lambda: republished.append(clock.now), clock=clock)
    assert made[:2] == ["episode", "map"] and [m[0] for m in made[2:]] == [1.0, 0.1]
    watch.on_status(messages.status_msg(IDS, 0, 0, Time(sec=1), Time(sec=1), session="mine"))
    assert health.sets == []  # its own status
    watch.on_status(messages.status_msg(IDS, 0, 0, Time(sec=1), Time(sec=1), session="theirs"))
    level, message = health.states["graph"]
    assert level == WARN and message.startswith("another driver publishes on /medc/episode (sessions "
                                                "theirs; this simulator is mine)")
    own = messages.grid_msg(torch.zeros((4, 4), dtype=torch.bool), Time(sec=2), 1.0)
    watch.own_map(own.info.map_load_time)
    watch.on_map(own)
    assert "map" not in health.states
    watch.on_map(messages.grid_msg(torch.zeros((4, 4), dtype=torch.bool), Time(sec=3), 1.0))
    assert health.level("map") == WARN and watch.foreign_maps == 1
    watch._republish()
    assert republished == []  # not yet: the agents see the foreign map first
    clock.now += REPUBLISH_DELAY_S
    watch._republish()
    assert republished == [clock.now]
    clock.now += CLEAR_S + 0.1
    watch._clear()
    assert health.states["graph"] == health.states["map"] == (OK, f"no other driver heard for {CLEAR_S:g} s")


def test_a_declaration_ends_the_episode_only_from_the_team_while_no_stranger_publishes():
    from medc_common import contract
    from medc_interfaces.msg import SourceDeclaration
    from medc_sim.declarations import Declarations
    from medc_sim.moves import MoveBook
    from medc_sim.sim_core import SimConfig, SimCore

    core = SimCore(SimConfig(agents=3, walls=0, grid=10, max_steps=50, seed=1, end_on="declaration"))
    topic = contract.declaration_topic("/medc")
    publishers = {contract.move_topic("/medc", a): [("/medc", f"medc_{a}")] for a in IDS}
    publishers[topic] = [("/medc", "medc_agent_0"), ("/medc", "spy")]

    def publishers_of(topic: str):
        return [SimpleNamespace(node_namespace=ns, node_name=name) for ns, name in publishers.get(topic, [])]

    log, health, finished, drops = _Log(), _Health(), [], []
    node = SimpleNamespace(get_logger=lambda: log, get_publishers_info_by_topic=publishers_of,
                           create_subscription=lambda *a: None)
    declarations = Declarations(node, None, "/medc", IDS, core, MoveBook(3, 8), health, running=lambda: True,
                                map_stamp=lambda: Time(sec=1), finish=finished.append,
                                drop=lambda: drops.append(1))

    def declaration(**kw):
        fields = dict(agent_id="agent_0", episode=core.episode, step=core.step, map_stamp=Time(sec=1),
                      cell_i=2, cell_j=3, mass=0.9)
        return SourceDeclaration(**{**fields, **kw})

    declarations.on_declaration(declaration())  # a node that moves no agent publishes declarations too
    level, message = health.states["declarations"]
    assert level == WARN and message.startswith("declaration refused: 1 node(s) that move no agent publish "
                                                f"on {topic} (/medc/spy)")
    assert drops == [1] and declarations.refused == 1 and finished == []
    declarations.on_declaration(declaration(episode=core.episode + 1))  # not the episode in play
    assert drops == [1] and log.said("warning")[-1].startswith("dropped declaration for episode 1 step 0")
    publishers[topic].pop()  # the stranger is gone
    declarations.on_declaration(declaration())
    assert [r.episode for r in finished] == [0] and finished[0].ended_by == "declaration"
    assert health.states["declarations"] == (OK, "declaration of agent_0 taken") and declarations.taken == 1


def test_policy_swaps_start_runs_the_first_policy_or_refuses_to_start():
    from medc_agents.policy_slot import PolicyRejected

    swaps, log, _ = _swaps([])
    with pytest.raises(PolicyRejected, match=r"policy 'notes\.txt' refused, not starting: notes\.txt is no"):
        swaps.start("notes.txt")
    assert swaps.slot.current is None and swaps.observer.observation is None
    swaps.start("team.safetensors")
    assert swaps.slot.current.description == "bundle team.safetensors"
    assert swaps.observer.observation.name == "maps" and log.lines == []  # the node logs the start


class _FailingSlot:
    """A policy slot whose policy fails on a mask with no valid move and picks the first one else."""

    controller = None

    def act(self, obs, mask):
        if not mask.any():
            raise RuntimeError("no valid move")
        return int(mask.nonzero()[0, 0])


def test_the_decider_plays_the_policy_and_keeps_what_it_failed_on_for_the_resent_step():
    from medc_agents.node import Decider, MoveOut
    from medc_agents.team_episode import Tick

    sent, log = [], _Log()
    moves = MoveOut("agent_0", "me", sent.append, lambda: Time(sec=1))
    decider = Decider(_FailingSlot(), None, moves, False, log)
    t0, t1 = Tick(1, 0, 10, 1), Tick(1, 1, 11, 1)
    assert decider.decide("obs", torch.tensor([False, False, True]), t0) == 2 and moves.unanswered is None
    none = torch.zeros(3, dtype=torch.bool)
    assert decider.decide("obs1", none, t1) is None
    assert moves.unanswered == ("obs1", none, t1) and sent == []
    assert log.said("error") == ["policy failed on episode 1 step 1: no valid move"]


def test_map_faults_take_a_map_or_count_and_report_its_refusal():
    from medc_agents.map_faults import MapFaults

    o, health, dropped = TeamObserver("agent_0", 3, 10), _Health(), Counter()
    faults = MapFaults(o, health, _Log(), dropped)
    small = messages.grid_msg(torch.zeros((8, 8), dtype=torch.bool), Time(sec=2), 1.0)
    assert faults.take(small) is False and dropped["map"] == 1
    level, message = health.states["map"]
    assert level == WARN and "map with map_load_time 2.000000000 refused" in message
    good = messages.grid_msg(torch.zeros((10, 10), dtype=torch.bool), Time(sec=3), 1.0)
    assert faults.take(good) is True and dropped["map"] == 1 and 3_000_000_000 in faults.checks


class _Auth:
    """Whether the team signs, and what it refused, as medc_common.auth_node's checker keeps them."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.refused: list[tuple[str, str]] = []

    def refuse(self, kind: str, why: str) -> None:
        self.refused.append((kind, why))


def test_signed_inputs_hold_a_pose_until_its_signed_reading_vouches_for_it():
    from medc_agents.signed_inputs import SignedInputs
    from medc_common.auth_node import message_digest
    from medc_common.contract import GridGeometry

    geometry = GridGeometry(10, 10, 1.0)
    pose = messages.pose_msg((1, 2), Time(sec=5), geometry)
    plain = SignedInputs(_Auth(False))
    assert plain.pose("agent_1", pose) is pose and plain.pose_of("agent_1", messages.reading_msg(
        "agent_1", 1.0, 0.0, Time(sec=5))) is None
    signed = SignedInputs(_Auth(True))
    assert signed.pose("agent_1", pose) is None  # held
    reading = messages.reading_msg("agent_1", 1.0, 0.0, Time(sec=5))
    reading.pose_digest = list(message_digest(pose))
    assert signed.pose_of("agent_1", reading) is pose
    other = messages.pose_msg((3, 3), Time(sec=5), geometry)  # another pose for the vouched stamp
    assert signed.pose("agent_1", other) is None
    assert signed.auth.refused and signed.auth.refused[0][0] == "pose"


def test_a_pose_off_every_map_has_each_maps_reason():
    from medc_agents.team_messages import pose_refusals
    from medc_common.contract import GridGeometry

    here, far = GridGeometry(10, 10, 1.0), GridGeometry(10, 10, 1.0, origin_x=500.0)
    assert pose_refusals((2.5, 3.5), [far, here], 0.5) is None
    assert pose_refusals((2.5, 3.5), [], 0.5) == []
    refusals = pose_refusals((-3.0, 3.5), [here, far], 0.5)
    assert len(refusals) == 2 and all(isinstance(r, ValueError) for r in refusals)
    assert pose_refusals((-0.4, 3.5), [here], 0.5) is None  # within the edge tolerance
