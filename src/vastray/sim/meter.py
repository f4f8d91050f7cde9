"""What a virtual node's own code costs between the work the cost model names.

The simulator runs each node's real code (its frame loop, the film it adds paths to, the
batches it cuts for its peers, its termination waves) and charges the named work apart:
traces and decisions at the CPU time they take here (``CostModel.trace_scale``,
``decision_scale``), loads and messages by the calibration's constants. Everything else a node
computes was charged as nothing, and a real node pays it on its event loop's thread: on the
turbine-blade scan's 2-node ``async`` render about 10 ms of 130 ms a node (two tiles' films of
49,152 paths folded in, the batches cut, the queues filled), which left every out-of-sample
row under-predicted.

``NodeMeter`` measures it: every step of a task that runs for a virtual node (the node's own
coroutines and the tasks they start: the context variable ``NODE`` names the node, and tasks
inherit it) is timed in this thread's CPU seconds (``launch.cpu_time``), less what its steps
charged another way (``account``: a trace's or a decision's CPU, the simulator's own
decoding of a sent batch and its cores' bookkeeping: ``simulators_own``), and the rest
waits in ``pending`` until the node's next charge on its cores takes it along
(``Cluster.compute``) or the node flushes it (the end of its busy span). Tasks the simulator
starts for itself (a message's arrival) run in a context without ``NODE`` and are charged to
no one, nor are its garbage collections (``collections_apart``).
"""

from __future__ import annotations

import asyncio
import contextvars
import gc
import types
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager

from vastray.scene.embree.launch import cpu_time

#: Node steps between two garbage collections while ``collections_apart`` holds them (every
#: tenth of all generations); a collection between steps is charged to no node.
COLLECT_EVERY_STEPS = 2000

#: The virtual node a task runs for (None: the simulator's own tasks).
NODE: contextvars.ContextVar[int | None] = contextvars.ContextVar("vastray_sim_node",
                                                                   default=None)


class NodeMeter:
    """Per virtual node: the CPU seconds its code took here beyond what was charged apart.

    Parameters
    ----------
    scale : virtual seconds charged per such CPU second (``CostModel.node_cpu_scale``).
    """

    def __init__(self, scale: float):
        self.scale = scale
        #: rank -> CPU seconds measured and not yet charged
        self.pending: defaultdict[int, float] = defaultdict(float)
        #: rank -> CPU seconds measured in all
        self.measured: defaultdict[int, float] = defaultdict(float)
        self._steps = 0

    def account(self, rank: int, cpu_seconds: float) -> None:
        """``cpu_seconds`` that node ``rank``'s measured steps spent (this one or an earlier
        one: a bookkeeping charged with the next decision) are charged another way (nothing
        to do where nothing is measured: ``scale`` 0)."""
        if not self.scale:
            return
        self.pending[rank] -= cpu_seconds
        self.measured[rank] -= cpu_seconds

    @contextmanager
    def collections_apart(self) -> Iterator[None]:
        """While in the block, this process collects its garbage between the nodes' steps,
        never inside one: a collection's pause grows with every virtual node's objects
        (60-90 ms with 64 nodes of the 1,439-domain store), and inside a step it was charged
        to whichever node's code (or trace, or decision) it interrupted, so the busiest
        node's time was one collection's; a real node collects only its own. Nothing changes
        where nothing is measured (``scale`` 0)."""
        if not self.scale:
            yield
            return
        enabled = gc.isenabled()
        gc.disable()
        try:
            yield
        finally:
            if enabled:
                gc.enable()

    def _collect_between_steps(self) -> None:
        self._steps += 1
        if self._steps % COLLECT_EVERY_STEPS == 0:  # a loop callback: outside every step
            asyncio.get_running_loop().call_soon(gc.collect, 1 if self._steps % (
                10 * COLLECT_EVERY_STEPS) else 2)

    def simulators_own(self) -> _SimulatorsOwn:
        """A block whose CPU is the simulator's own work (its cores' and network's
        bookkeeping, its decoding of a sent batch), not the node's whose step runs it:
        ``with meter.simulators_own(): ...``."""
        return _SimulatorsOwn(self)

    def take(self, rank: int) -> float:
        """Virtual seconds to charge node ``rank`` for what it computed since the last take
        (0 while what was accounted exceeds it: the rest waits)."""
        seconds = self.pending[rank]
        if seconds <= 0.0:
            return 0.0
        self.pending[rank] = 0.0
        return seconds * self.scale

    def task_factory(self, loop: asyncio.AbstractEventLoop, coro, context=None) -> asyncio.Task:
        """The loop's task factory: a task started for a virtual node (``NODE`` set in its
        context) has its steps measured."""
        context = contextvars.copy_context() if context is None else context
        rank = context.get(NODE)
        if rank is not None:
            coro = self._measured(coro, rank)
        return asyncio.Task(coro, loop=loop, context=context)

    @types.coroutine
    def _measured(self, coro, rank: int):
        """``coro``, each of its steps' CPU added to ``pending[rank]`` (what ``account``
        takes off)."""
        value, error = None, None
        while True:
            start = cpu_time()
            try:
                yielded = coro.send(value) if error is None else coro.throw(error)
            except StopIteration as stop:
                self._add(rank, cpu_time() - start)
                return stop.value
            except BaseException:
                self._add(rank, cpu_time() - start)
                raise
            self._add(rank, cpu_time() - start)
            try:
                value, error = (yield yielded), None
            except BaseException as exc:  # a cancellation, thrown into the coroutine
                value, error = None, exc

    def _add(self, rank: int, spent: float) -> None:
        self.pending[rank] += spent
        self.measured[rank] += spent
        if not gc.isenabled():
            self._collect_between_steps()


class _SimulatorsOwn:
    """``NodeMeter.simulators_own``'s block: its CPU accounted to the node whose step runs it
    (none outside a node's task; the clock not read where nothing is measured)."""

    __slots__ = ("meter", "start")

    def __init__(self, meter: NodeMeter):
        self.meter, self.start = meter, 0.0

    def __enter__(self) -> None:
        if self.meter.scale:
            self.start = cpu_time()

    def __exit__(self, *exc) -> None:
        rank = NODE.get() if self.meter.scale else None
        if rank is not None:
            self.meter.account(rank, cpu_time() - self.start)


def start_node_task(loop: asyncio.AbstractEventLoop, rank: int, coro) -> asyncio.Task:
    """Start ``coro`` as virtual node ``rank``'s task (measured where the loop's task factory
    is a ``NodeMeter``'s)."""
    context = contextvars.copy_context()
    context.run(NODE.set, rank)
    return loop.create_task(coro, context=context)


def start_simulator_task(coro) -> asyncio.Task:
    """Start ``coro`` as the simulator's own task: charged to no node."""
    return asyncio.get_running_loop().create_task(coro, context=contextvars.Context())
