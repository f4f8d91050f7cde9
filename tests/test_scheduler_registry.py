"""The scheduler registry (``schedule/registry.py``): every scheduler declared once, its
attributes consistent with the runtimes, option checks and CLI that read them, and no
scheduler-name string comparison anywhere else in the production source."""

from __future__ import annotations

import argparse
import importlib
import re
from pathlib import Path

import pytest

from vastray.actors import job_options
from vastray.actors.job_options import JobOptions, JobOptionsError
from vastray.scene.errors import InputError
from vastray.schedule import registry
from vastray.schedule.registry import (
    JOB_SCHEDULERS,
    RENDER_CHOICES,
    SIMULATE_CHOICES,
    SPECS,
    Decomposition,
    Option,
    Runtime,
    Simulation,
    UnknownScheduler,
)

ROOT = Path(__file__).resolve().parent.parent
#: The production source the registry's rule holds for.
PRODUCTION = ("actors", "render", "schedule", "scene", "transport", "src/vastray")
#: Where the names are declared (the one place they may be compared).
REGISTRY = "schedule/registry.py"
#: Files still allowed to compare names: none (every file reads the registry, issue 42).
ALLOWED: set[str] = set()

_NAMES = "|".join(re.escape(s.name) for s in SPECS)
#: A scheduler variable compared with a name or a tuple of names: ``options.scheduler ==
#: "image"``, ``scheduler in ("a", "b")``, ``self.scheduler not in TILE_SCHEDULERS`` (not a
#: loop, ``for scheduler in ...``).
VARIABLE = re.compile(r"(?<!for )(?<![\w.])[\w.]*sched[\w.]*\)?\s+(==|!=|not in|in)\s+[(\[{\"'A-Z]")
#: A scheduler name compared, whatever the variable: ``mode == "spec-ooc"``,
#: ``"temporal" != kind`` (``domain``, ``image``, ``reference``, ``async`` and ``auto`` are
#: words too common to look for alone; the variable rule and the tuple rule catch them).
LITERAL = re.compile(r"(==|!=|\bin|\bis)\s*[(\[{]?\s*[\"'](spec-ooc|spec-insitu|temporal|dynamic)"
                     r"[\"']|[\"'](spec-ooc|spec-insitu|temporal|dynamic)[\"']\s*(==|!=|not in\b|in\b)")
#: A tuple, list or set of two or more scheduler names: ``TILE_SCHEDULERS = ("image",
#: "spec-ooc")``, ``choices=["auto", "reference", ...]``.
TUPLE = re.compile(rf"[(\[{{]\s*[\"']({_NAMES})[\"']\s*,\s*[\"']({_NAMES})[\"']")


def offences(text: str) -> list[str]:
    """The lines of ``text`` that compare scheduler names or list them."""
    return [line.strip() for line in text.splitlines()
            if VARIABLE.search(line) or LITERAL.search(line) or TUPLE.search(line)]


# -- the registry's own consistency -----------------------------------------------------------


def test_each_name_is_declared_once_and_found_by_spec():
    names = [s.name for s in SPECS]
    assert len(names) == len(set(names))
    for s in SPECS:
        assert registry.spec(s.name) is s
        assert registry.find(s.name) is s
    assert registry.find("nope") is None and registry.find(None) is None


def test_an_unknown_name_is_refused_with_the_valid_names():
    with pytest.raises(UnknownScheduler) as caught:
        registry.spec("imgae")
    assert isinstance(caught.value, InputError)
    assert str(caught.value) == ("unknown scheduler 'imgae'; choose from "
                                 + ", ".join(s.name for s in SPECS))


def test_the_cli_offers_the_registrys_names_in_its_order():
    from vastray.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    render = next(a for a in sub.choices["render"]._actions if a.dest == "scheduler")
    assert tuple(render.choices) == RENDER_CHOICES
    assert render.default in RENDER_CHOICES
    simulate = next(a for a in sub.choices["simulate"]._actions if a.dest == "scheduler")
    assert ", ".join(SIMULATE_CHOICES) in simulate.help
    assert simulate.type(",".join(SIMULATE_CHOICES)) == list(SIMULATE_CHOICES)
    for name in set(RENDER_CHOICES) - set(SIMULATE_CHOICES):
        with pytest.raises(argparse.ArgumentTypeError):
            simulate.type(name)


def test_the_name_tuples_follow_the_declarations():
    assert RENDER_CHOICES == tuple(s.name for s in SPECS)
    assert JOB_SCHEDULERS == tuple(s.name for s in SPECS if s.runtime is not Runtime.RESOLVED)
    assert set(SIMULATE_CHOICES) == {s.name for s in SPECS if s.simulation is not None}
    assert len(SIMULATE_CHOICES) == len(set(SIMULATE_CHOICES))
    from vastray.sim.simulate import SIM_SCHEDULERS

    assert SIM_SCHEDULERS == SIMULATE_CHOICES


def test_a_resolved_name_stands_for_job_schedulers():
    for s in SPECS:
        if s.runtime is Runtime.RESOLVED:
            assert s.resolves is not None
            for fits in (True, False):
                assert registry.resolve(s.name, fits) in JOB_SCHEDULERS
            assert not s.options and s.simulation is None and s.decomposition is None
        else:
            assert s.resolves is None
            assert registry.resolve(s.name, True) == registry.resolve(s.name, False) == s.name
    assert registry.resolve("auto", True) == "reference"
    assert registry.resolve("auto", False) == "spec-ooc"


def test_each_runtime_kind_has_a_runner():
    from vastray.actors.node import NODE_RUNTIMES
    from vastray.sim.simulate import SIMULATION_RUNNERS

    kinds = {s.runtime for s in SPECS}
    assert kinds == set(Runtime)
    for s in SPECS:
        if s.runtime.on_nodes:
            assert s.runtime in NODE_RUNTIMES, s.name
        if s.simulation is not None:
            assert s.simulation in SIMULATION_RUNNERS, s.name
        assert registry.spec(s.on_nodes).runtime.on_nodes or s.runtime is Runtime.RESOLVED
        # a domain-decomposed scheduler says how its frames move rays; no other does
        assert (s.decomposition is not None) == (s.runtime is Runtime.DOMAINS), s.name
    assert {s.decomposition for s in SPECS} - {None} == set(Decomposition)
    assert {s.simulation for s in SPECS} - {None} == set(Simulation)


def test_the_simulator_runs_each_scheduler_as_its_runtime_does():
    same = {Runtime.TILES: Simulation.SORT_FIRST, Runtime.DOMAINS: Simulation.DOMAINS,
            Runtime.IN_SITU: Simulation.IN_SITU}
    for s in SPECS:
        assert s.simulation is same.get(s.runtime), s.name


def test_every_scheduler_is_lossless_and_only_a_speculating_tile_schedule_evicts():
    for s in SPECS:
        assert s.lossless, s.name
        if s.evicts:
            assert s.speculates and s.runtime is Runtime.TILES, s.name
        if s.accepts(Option.HISTORY_DEPTH):
            assert s.speculates and s.runtime is Runtime.TILES, s.name


@pytest.mark.parametrize("s", SPECS, ids=lambda s: s.name)
def test_the_policies_named_exist(s):
    for dotted in s.policies:
        module, _, attribute = dotted.rpartition(".")
        try:
            importlib.import_module(dotted)
        except ImportError:
            assert hasattr(importlib.import_module(module), attribute), dotted


def test_assignments_and_priorities_are_the_plans():
    from vastray.schedule import temporal

    for s in SPECS:
        assert set(s.assignments) <= set(job_options.ASSIGNMENTS), s.name
        assert set(s.priorities) <= set(job_options.PRIORITIES), s.name
        assert s.default_assignment is None or s.default_assignment in s.assignments
        assert s.default_priority is None or s.default_priority in s.priorities
    planner = registry.spec("temporal")
    assert planner.assignments == temporal.ASSIGNMENTS == job_options.ASSIGNMENTS
    assert planner.priorities == temporal.PRIORITIES == job_options.PRIORITIES
    assert (planner.default_assignment, planner.default_priority) == ("affinity", "cost-rate")


#: The JobOptions fields that give each option JobOptions checks.
GIVEN = {
    Option.SAMPLES_IN_FLIGHT: {"max_samples_in_flight": 10},
    Option.NO_PRELOAD: {"preload": False},
    Option.COLD_READS: {"cold_reads": True},
    Option.RESIDENT_FIRST: {"resident_first": False},
    Option.MAX_BATCH_RAYS: {"max_batch_rays": 100},
    Option.EVICTION: {"eviction": "demand"},
    Option.HISTORY_DEPTH: {"history_depth": 1},
    Option.SIMPLIFIED: {"simplified": "none"},
}


@pytest.mark.parametrize("name", JOB_SCHEDULERS)
def test_job_options_accept_exactly_the_declared_options(name):
    s = registry.spec(name)
    for option, given in GIVEN.items():
        if s.accepts(option):
            JobOptions(scheduler=name, **given)
        else:
            with pytest.raises(JobOptionsError):
                JobOptions(scheduler=name, **given)
    for assignment in job_options.ASSIGNMENTS:
        if assignment in s.assignments:
            JobOptions(scheduler=name, assignment=assignment)
        else:
            with pytest.raises(JobOptionsError, match="--assignment"):
                JobOptions(scheduler=name, assignment=assignment)
    for priority in job_options.PRIORITIES:
        if priority in s.priorities:
            JobOptions(scheduler=name, priority=priority)
        else:
            with pytest.raises(JobOptionsError, match="--priority"):
                JobOptions(scheduler=name, priority=priority)


def test_job_options_refuse_a_name_resolved_before_the_job():
    for s in SPECS:
        if s.runtime is Runtime.RESOLVED:
            with pytest.raises(JobOptionsError, match="choose from " + ", ".join(JOB_SCHEDULERS)):
                JobOptions(scheduler=s.name)


# -- no scheduler-name comparisons outside the registry ---------------------------------------


@pytest.mark.parametrize("line", [
    'if options.scheduler == "image":',
    'if scheduler in ("a", "b"):',
    'if scheduler != "temporal":',
    '    if self.scheduler not in TILE_SCHEDULERS + NODE_ONLY_SCHEDULERS:',
    'tiles = args.scheduler in ["spec-ooc", "auto"]',
    'x = sched.name == "async"',
    'if mode == "spec-ooc":',
    'elif "temporal" != kind:',
    'TILE_SCHEDULERS = ("image", "spec-ooc")',
    'p.add_argument("--scheduler", choices=["auto", "reference", "image"])',
    'MODES = {"domain", "async"}',
])
def test_the_pattern_catches_a_comparison(line):
    assert offences(line) == [line.strip()]


@pytest.mark.parametrize("line", [
    "for scheduler in args.scheduler:",
    "if sched.runtime is Runtime.TILES:",
    "sched = registry.spec(options.scheduler)",
    'options = JobOptions(scheduler="image")',
    'scheduler: str = "image",',
    'domains = arrays.get("domain")',
    'if not sched.accepts(Option.EVICTION):',
    'scheduler = options.scheduler',
])
def test_the_pattern_passes_what_is_no_comparison(line):
    assert offences(line) == []


def test_no_scheduler_name_is_compared_outside_the_registry():
    found = []
    for folder in PRODUCTION:
        for path in sorted((ROOT / folder).rglob("*.py")):
            relative = path.relative_to(ROOT).as_posix()
            if relative == REGISTRY or relative in ALLOWED:
                continue
            found += [f"{relative}: {line}" for line in offences(path.read_text())]
    assert not found, ("scheduler names compared outside schedule/registry.py (read the "
                       "scheduler's attributes instead):\n" + "\n".join(found))
