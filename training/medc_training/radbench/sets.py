"""The frozen benchmark sets: their file format, the loader that checks their SHA-256, and the writer.

A set file holds every set of one area and team size (``g20-a1.json``: 20 x 20 cells, 1 agent):
24 sets, obstruction counts 0-7 x SNR bins low, medium, high, of 200 episodes each. It is JSON::

    {"format": "medc-radbench/1", "grid": 20, "cell_m": 1.0, "agents": 1, "max_steps": 120,
     "physics": {...}, "generator": {"seed": 2021, "episodes": 200, ...},
     "sets": [{"id": "obs0-low", "obstructions": 0, "snr": "low", "sha256": "...",
               "stats": {...}, "episodes": [
       {"src": [r, c], "S": 523.17, "B": 31, "starts": [[r, c]], "obs": [[top, left, bottom, right]],
        "seed": 1234567890},
       ...]}, ...]}

(one episode per line). ``S`` is the source strength in counts/s at 1 m, ``B`` the background in
counts/s, ``seed`` the episode's count-noise seed (:class:`~medc_training.radbench.scenario.Episode`).
A set's ``sha256`` is the digest of its canonical form (:func:`set_digest`: its id, area, team size,
step limit and episodes as compact JSON with sorted keys), the name results carry.

The committed files are data the results depend on: :data:`FROZEN` holds the SHA-256 of each file's
bytes, and :func:`load_file` refuses a file whose bytes do not hash to it (and any set whose digest
does not match its episodes), saying how to restore it. ``medc-radbench --generate DIR`` writes them
again (the same bytes, from the same seed).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .scenario import (
    DEFAULT_SEED,
    GRIDS,
    MAX_STEPS,
    OBSTRUCTION_COUNTS,
    PHYSICS,
    SNR_BINS,
    SNR_NAMES,
    Episode,
    generate_set,
)

__all__ = [
    "FORMAT",
    "FROZEN",
    "SETS_DIR",
    "BenchSet",
    "SetFileError",
    "add_set_arguments",
    "file_name",
    "file_sha256",
    "generate_file",
    "load_file",
    "load_sets",
    "set_digest",
    "set_id",
    "sets_from_args",
    "write_file",
]

FORMAT = "medc-radbench/1"
#: Where the frozen set files live.
SETS_DIR = Path(__file__).resolve().parent / "sets"
#: SHA-256 of the bytes of each frozen set file: a file that hashes otherwise is refused.
FROZEN: dict[str, str] = {
    "g20-a1.json": "8408570dd44dc8cb54fbd73e305048d89c9c54d4e6524ee3ebd1c40bc648b64b",
    "g20-a3.json": "e5b7f03ee2f3e0183c3aa4377288507ae8f3c008fdb7aede2325353b7b1736f5",
    "g30-a1.json": "93db41a4d71bc69e7667d8a94864cebe4d8ebe8f79d86d6503f0e06b64d1be8d",
    "g30-a3.json": "6b1d7dc77df3ffe1e0c8029a6dfcb9f5369e18765f33a2d32db44e648c1c3af1",
}
#: Episodes per frozen set.
FROZEN_EPISODES = 200


class SetFileError(ValueError):
    """A set file that cannot be used as it is (changed, malformed, or not a frozen set's)."""


@dataclass(frozen=True)
class BenchSet:
    """One benchmark set: ``episodes`` on a ``grid`` x ``grid`` area for ``agents`` agents, all with
    ``obstructions`` obstructions and a start SNR in bin ``snr``; ``sha256`` its digest
    (:func:`set_digest`), ``source`` the file it came from (with that file's SHA-256); ``first`` the
    index in the whole set of ``episodes[0]`` (0 but for a :meth:`part`), which episode lines carry."""

    id: str
    grid: int
    cell_m: float
    agents: int
    max_steps: int
    obstructions: int
    snr: str
    episodes: tuple[Episode, ...]
    sha256: str
    source: str = ""
    file_sha256: str = ""
    first: int = 0

    def head(self, count: int) -> BenchSet:
        """The first ``count`` episodes (a balanced subset when ``count`` is a multiple of 4: episode
        i comes from SNR sub-bin i % 4); the digest stays the whole set's, the id says the subset."""
        return self.part(0, count)

    def part(self, start: int, count: int | None = None) -> BenchSet:
        """``count`` episodes (all that are left when None) from episode ``start`` on, each keeping its
        index in the whole set (a balanced subset when both are multiples of 4); the id says the
        subset (``obs5-low[40:100]``; ``[:N]`` from episode 0, as :meth:`head`). ValueError for a
        negative ``start`` or one at or past the set's end, or a ``count`` below 1."""
        if self.first:
            raise ValueError(f"set {self.id} is already a part of its set")
        if isinstance(start, bool) or not isinstance(start, int) or not 0 <= start < len(self.episodes):
            raise ValueError(f"the first episode must be 0..{len(self.episodes) - 1} (set {self.id} has "
                             f"{len(self.episodes)}), got {start!r}")
        stop = len(self.episodes) if count is None else start + count
        if count is not None and count < 1:
            raise ValueError(f"a part of a set needs at least one episode, got {count!r}")
        if start == 0 and stop >= len(self.episodes):
            return self
        stop = min(stop, len(self.episodes))
        name = f"{self.id}[:{stop}]" if start == 0 else f"{self.id}[{start}:{stop}]"
        return BenchSet(name, self.grid, self.cell_m, self.agents, self.max_steps, self.obstructions,
                        self.snr, self.episodes[start:stop], self.sha256, self.source, self.file_sha256,
                        start)


def set_id(obstructions: int, snr: str) -> str:
    """The id of the set with ``obstructions`` obstructions in SNR bin ``snr``: ``obs3-medium``."""
    return f"obs{obstructions}-{snr}"


def file_name(grid: int, agents: int) -> str:
    """The frozen file of ``grid`` and ``agents``: ``g20-a1.json``."""
    return f"g{grid}-a{agents}.json"


def set_digest(set_id_: str, grid: int, agents: int, max_steps: int, episodes: Iterable[Episode]) -> str:
    """SHA-256 (hex) of a set's canonical form: compact JSON with sorted keys of its id, area, team
    size, step limit and episodes (:meth:`Episode.to_json`)."""
    body = {"id": set_id_, "grid": grid, "agents": agents, "max_steps": max_steps,
            "episodes": [e.to_json() for e in episodes]}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def file_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


# ------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------


def generate_file(grid: int, agents: int, episodes: int = FROZEN_EPISODES, seed: int = DEFAULT_SEED,
                  obstructions: Sequence[int] = OBSTRUCTION_COUNTS, snrs: Sequence[str] = tuple(SNR_BINS),
                  progress=None) -> dict[str, Any]:
    """The JSON document of a set file: every (obstruction count, SNR bin) set of ``grid`` and
    ``agents``. ``progress`` (a callable) is called once per set generated."""
    sets = []
    for count in obstructions:
        for name in snrs:
            drawn, stats = generate_set(grid, agents, count, name, episodes, seed)
            sid = set_id(count, name)
            sets.append({"id": sid, "obstructions": count, "snr": name,
                         "sha256": set_digest(sid, grid, agents, MAX_STEPS, drawn),
                         "stats": stats.to_json(), "episodes": [e.to_json() for e in drawn]})
            if progress is not None:
                progress()
    return {"format": FORMAT, "grid": grid, "cell_m": GRIDS[grid].cell_m, "agents": agents,
            "max_steps": MAX_STEPS, "physics": PHYSICS,
            "generator": {"module": "medc_training.radbench.scenario", "seed": seed, "episodes": episodes},
            "sets": sets}


def write_file(document: dict[str, Any], path: str | Path) -> str:
    """Write a set file (one episode per line) and return its SHA-256."""
    head = {k: v for k, v in document.items() if k != "sets"}
    lines = ["{", *(f"  {json.dumps(k)}: {json.dumps(v, sort_keys=True)}," for k, v in head.items()),
             '  "sets": [']
    for i, s in enumerate(document["sets"]):
        meta = {k: v for k, v in s.items() if k != "episodes"}
        lines.append("    " + json.dumps(meta, sort_keys=True)[:-1] + ', "episodes": [')
        eps = [json.dumps(e, sort_keys=True, separators=(",", ":")) for e in s["episodes"]]
        lines += [f"      {e}," for e in eps[:-1]] + [f"      {eps[-1]}"]
        lines.append("    ]}" + ("," if i < len(document["sets"]) - 1 else ""))
    lines += ["  ]", "}", ""]
    data = "\n".join(lines).encode()
    json.loads(data)  # what is written must read back
    target = Path(path)
    tmp = target.with_name(target.name + ".tmp")
    tmp.write_bytes(data)
    tmp.replace(target)
    return hashlib.sha256(data).hexdigest()


# ------------------------------------------------------------------------------------------
# loading
# ------------------------------------------------------------------------------------------


def _frozen_path(grid: int, agents: int) -> Path:
    name = file_name(grid, agents)
    if name not in FROZEN:
        have = ", ".join(sorted(FROZEN))
        raise SetFileError(f"no frozen sets for grid {grid} with {agents} agent(s); the frozen files are "
                           f"{have}")
    return SETS_DIR / name


def load_file(path: str | Path | None = None, *, grid: int | None = None, agents: int | None = None,
              sha256: str | None = None) -> tuple[list[BenchSet], str]:
    """(every set of a set file, the file's SHA-256), each set checked against its digest.

    Give ``grid`` and ``agents`` for the frozen file (:data:`SETS_DIR`), or a ``path``. A frozen
    file's bytes must hash to :data:`FROZEN`; any other file's to ``sha256`` when given. Raises
    SetFileError saying what is wrong and what to do.
    """
    if path is None:
        if grid is None or agents is None:
            raise SetFileError("load_file needs a path, or grid= and agents= for a frozen set file")
        path = _frozen_path(grid, agents)
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SetFileError(f"cannot read the set file {path}: {exc.strerror or exc}") from None
    digest = hashlib.sha256(data).hexdigest()
    expected = sha256
    frozen = FROZEN.get(path.name) if path.resolve().parent == Path(SETS_DIR).resolve() else None
    if frozen is not None:
        expected = frozen
    if expected is not None and digest != expected:
        how = ("restore it with `git checkout -- " + str(path) + "` (or regenerate it with "
               "`medc-radbench --generate DIR` and review the difference)") if frozen is not None else \
              "use the file whose hash you were given"
        raise SetFileError(f"the set file {path} was changed: its SHA-256 is {digest}, expected {expected}; "
                           f"{how}")
    try:
        doc = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SetFileError(f"the set file {path} is not JSON ({exc}); restore or regenerate it") from None
    return _parse(doc, path, digest), digest


def _parse(doc: Any, path: Path, digest: str) -> list[BenchSet]:
    def bad(what: str) -> SetFileError:
        return SetFileError(f"the set file {path} is malformed: {what}; restore or regenerate it")

    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise bad(f"its format is not {FORMAT!r}")
    grid, agents, max_steps = doc.get("grid"), doc.get("agents"), doc.get("max_steps")
    cell_m = doc.get("cell_m")
    if grid not in GRIDS or cell_m != GRIDS[grid].cell_m:
        raise bad(f"grid {grid!r} with cell {cell_m!r} m is not a benchmark area ({sorted(GRIDS)}, "
                  "1 m cells)")
    if not isinstance(agents, int) or isinstance(agents, bool) or not 1 <= agents <= 8:
        raise bad(f"agents must be an integer in 1..8, got {agents!r}")
    if not isinstance(max_steps, int) or isinstance(max_steps, bool) or not 1 <= max_steps <= 100_000:
        raise bad(f"max_steps must be a positive integer, got {max_steps!r}")
    if not isinstance(doc.get("sets"), list):
        raise bad("it has no list of sets")
    out: list[BenchSet] = []
    for s in doc["sets"]:
        if not isinstance(s, dict) or not isinstance(s.get("episodes"), list) or not s["episodes"]:
            raise bad("a set without episodes")
        sid, count, name = s.get("id"), s.get("obstructions"), s.get("snr")
        if count not in OBSTRUCTION_COUNTS or name not in SNR_NAMES or sid != set_id(count, name):
            raise bad(f"set {str(sid)[:40]!r} has obstructions {count!r} and SNR bin {str(name)[:20]!r}")
        try:
            episodes = tuple(Episode.from_json(e, grid) for e in s["episodes"])
        except ValueError as exc:
            raise bad(f"set {sid}: {exc}") from None
        if any(len(e.starts) != agents or len(e.obstructions) != count for e in episodes):
            raise bad(f"set {sid} has an episode with another team size or obstruction count")
        want = set_digest(sid, grid, agents, max_steps, episodes)
        if s.get("sha256") != want:
            raise SetFileError(f"set {sid} of {path} does not match its digest (its episodes hash to {want}, "
                               f"it records {str(s.get('sha256'))[:64]}): restore or regenerate the file")
        out.append(BenchSet(sid, grid, float(cell_m), agents, max_steps, count, name, episodes, want,
                            str(path), digest))
    ids = [b.id for b in out]
    if len(set(ids)) != len(ids):
        raise bad("a set id appears twice")
    return out


def load_sets(grid: int = 20, agents: int = 1, obstructions: Iterable[int] | None = None,
              snrs: Iterable[str] | None = None, path: str | Path | None = None,
              sha256: str | None = None) -> list[BenchSet]:
    """The frozen sets of ``grid`` and ``agents`` (or of the file at ``path``, whose bytes must hash
    to ``sha256`` when given), those with the given obstruction counts and SNR bins (all when None),
    in file order, hash-checked (:func:`load_file`)."""
    if path is None:
        sets, _ = load_file(grid=grid, agents=agents)
    else:
        sets, _ = load_file(path, sha256=sha256)
    counts = None if obstructions is None else set(obstructions)
    names = None if snrs is None else set(snrs)
    if names is not None and not names <= set(SNR_NAMES):
        raise SetFileError(f"unknown SNR bin(s) {sorted(names - set(SNR_NAMES))}; choose from "
                           f"{', '.join(SNR_BINS)}")
    picked = [s for s in sets
              if (counts is None or s.obstructions in counts) and (names is None or s.snr in names)]
    if not picked:
        raise SetFileError("no set matches those obstruction counts and SNR bins")
    return picked


def add_set_arguments(parser, *, obstructions: bool = False, sha256: bool = False) -> None:
    """The command-line options that choose the sets a diagnostic plays (:func:`sets_from_args`):
    the frozen file of ``--grid`` and ``--agents`` or ``--sets-file`` (with ``sha256``:
    ``--sha256``), with ``obstructions``: ``--obstructions``, and ``--episodes`` from ``--first``."""
    parser.add_argument("--grid", type=int, choices=(20, 30), default=20,
                        help="the frozen file's area (default 20)")
    parser.add_argument("--agents", type=int, choices=(1, 3), default=3,
                        help="the frozen file's team (default 3)")
    parser.add_argument("--sets-file", type=Path, help="a set file of your own instead of the frozen one")
    if sha256:
        parser.add_argument("--sha256", help="with --sets-file: the SHA-256 the file must have")
    if obstructions:
        parser.add_argument("--obstructions", type=int, nargs="+", help="only the sets of these counts")
    parser.add_argument("--episodes", type=int, help="the first N episodes of each set (default all)")
    parser.add_argument("--first", type=int, default=0,
                        help="with --episodes: start at this episode of each set (default 0; episode lines "
                             "keep each episode's index in its set)")


def sets_from_args(args) -> list[BenchSet]:
    """The sets :func:`add_set_arguments`'s options name, each cut to ``--episodes`` from its episode
    ``--first`` (named as ``medc-radbench --episodes`` names them; :meth:`BenchSet.part`). ValueError
    for a non-positive ``--episodes`` or a ``--first`` outside the sets; SetFileError as
    :func:`load_sets`."""
    if args.episodes is not None and args.episodes < 1:
        raise ValueError("--episodes must be positive")
    counts, digest = getattr(args, "obstructions", None), getattr(args, "sha256", None)
    if args.sets_file is not None:
        sets = load_sets(path=args.sets_file, sha256=digest, obstructions=counts)
    else:
        sets = load_sets(args.grid, args.agents, obstructions=counts)
    first = getattr(args, "first", 0)
    if args.episodes is None and not first:
        return sets
    return [s.part(first, args.episodes) for s in sets]
