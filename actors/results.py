"""A distributed render's result from its nodes' reports: the counters that sum or take the
most over nodes, the node losses survived (and the CLI's line for each), and a simplified-model
run's portal shares."""

from __future__ import annotations

from vastray.render.driver import RenderResult
from vastray.schedule.portals import Accuracy


def render_result(film, camera, reports: list[dict], scheduler: str,
                  size: int, asked: int, failures: list[str], wall: float,
                  recoveries: list[dict] = ()) -> RenderResult:
    """A render's result from the nodes' reports (of the job, or of one frame).

    ``recoveries`` : one entry per node lost so far (``node``, ``cause``, the ``frames`` done
    again on the others); the counters keep them and count the losses by cause
    (``node_deaths``, e.g. ``{"SIGSEGV": 1}``), so a recovery is never silent.
    """
    deaths: dict[str, int] = {}
    reports = list(reports) or [{"busy_s": 0.0, "reduce_s": 0.0, "counters": {}}]
    for entry in recoveries:
        deaths[entry["cause"]] = deaths.get(entry["cause"], 0) + 1
    counters = {"scheduler": scheduler, "nodes": size, "nodes_asked": asked,
                "node_failures": list(failures), "node_deaths": deaths,
                "recoveries": [dict(entry) for entry in recoveries], "per_node": reports,
                # what every node waits for all the others at (the nodes' tree rounds and
                # frame ends: the same count on every node)
                "global_barriers": max(r["counters"].get("global_barriers", 0)
                                       for r in reports),
                "loads": sum(r["counters"].get("loads", 0) for r in reports),
                "bytes_loaded": sum(r["counters"].get("bytes_loaded", 0) for r in reports),
                "load_throttle_s": round(sum(r["counters"].get("load_throttle_s", 0.0)
                                             for r in reports), 4),
                "load_wait_s": round(sum(r["counters"].get("load_wait_s", 0.0)
                                         for r in reports), 4),
                "peak_rss_bytes_max": max(r["counters"].get("peak_rss_bytes", 0)
                                          for r in reports)}
    held = [r["counters"]["cpu_throttled_s"] for r in reports
            if "cpu_throttled_s" in r["counters"]]
    if held:  # nodes under a CPU quota (a container's): the most throttled one's time
        counters["cpu_throttled_s_max"] = round(max(held), 4)
    for name in ("ahead_queries", "given_up_paths"):  # passes traced ahead (``node_ahead``)
        if any(name in r["counters"] for r in reports):
            counters[name] = sum(r["counters"].get(name, 0) for r in reports)
    counters.update(portal_shares([r["counters"] for r in reports]))
    seconds = {"total": round(wall, 4),
               "busy_max": max(r["busy_s"] for r in reports),
               "reduce_max": max(r["reduce_s"] for r in reports)}
    return RenderResult(film, camera, seconds, counters)


def recovery_lines(counters: dict) -> list[str]:
    """One line per node lost during a render, for the CLI's last lines: which frames were
    rendered again, after which node died and how (e.g. ``frame 0 re-rendered after node 1
    died (SIGSEGV)``); none when no node was lost."""
    lines = []
    for entry in counters.get("recoveries", []):
        frames = entry["frames"]
        which = (f"frame {frames[0]}" if len(frames) == 1 else
                 f"frames {frames[0]}-{frames[-1]}" if frames == list(range(frames[0],
                                                                             frames[-1] + 1))
                 else "frames " + ", ".join(map(str, frames)))
        node = "a node" if entry["node"] is None else f"node {entry['node']}"
        how = "stalled" if entry["cause"] == "stalled" else f"died ({entry['cause']})"
        lines.append(f"{which} re-rendered after {node} {how}")
    return lines


#: A node throttled by its CPU quota for this share of the busiest node's time or more is
#: said on the CLI's last lines (``quota_lines``).
HELD_SHARE = 0.05


def quota_lines(counters: dict, seconds: dict) -> list[str]:
    """A line for the CLI's last lines where a CPU quota throttled a node for
    ``HELD_SHARE`` of the busiest node's time or more (``cpu_throttled_s`` in the nodes'
    counters: their cgroups' throttled time over their busy spans,
    ``scene.cpus.cgroup_cpu_throttled_s``); none otherwise. 8 nodes of 0.25 CPU took 1.64x
    as long to render ``domain`` (its busiest node 2.2x) as the same nodes sharing the cores
    without a quota (``bench/compose_scale.py``, 2026-12-05)."""
    held = counters.get("cpu_throttled_s_max", 0.0)
    busy = seconds.get("busy_max", 0.0)
    if not held or held < HELD_SHARE * busy:
        return []
    nodes = [(node["counters"].get("cpu_throttled_s", 0.0), node.get("rank", i))
             for i, node in enumerate(counters.get("per_node", []))]
    worst = max(nodes)[1] if nodes else "?"
    return [f"a CPU quota throttled the nodes: up to {held:.2f} s of throttled time (node "
            f"{worst}, its cgroup's cpu.stat, over the cores) while the busiest node worked "
            f"{busy:.2f} s; give each node at least 1 CPU, or share the cores without a quota "
            "(docker compose: NODE_CPUS)"]


def closing_lines(counters: dict, seconds: dict) -> list[str]:
    """What the CLI and ``vastray.render`` say after a render's summary: its recoveries
    (never silent) and what a CPU quota held the nodes back (``quota_lines``)."""
    return recovery_lines(counters) + quota_lines(counters, seconds)


def portal_shares(per_node: list[dict]) -> dict:
    """A simplified-model run's shares from its nodes' counters (of a frame, or summed over
    frames); empty for other runs.

    * ``portal_resolution``: cells per portal edge (``--portal-resolution``).
    * ``simplified_share``: Simple/total, depth-1 portal crossings predicted low (sent to the
      simplified model) over all crossings; None where no ray crossed a portal (policies
      without portals). 0 in a recording frame, which predicts nothing.
    * ``acc`` and ``acc_simplified_share`` (instrumented ``portal_accuracy`` runs only): the
      share of crossings whose predicted class matches the actual one, and the share
      predicted low, classified with the portals a timed run predicts the frame with
      (``schedule.portals.prediction_accuracy``), and ``acc_unrecorded_share`` the share
      whose cell those portals never recorded (predicted high); ``replay_acc`` and
      ``replay_false_low`` classify with the frame's own recorded portals.
    """
    out = {}
    if any("portal_resolution" in c for c in per_node):
        out["portal_resolution"] = max(c.get("portal_resolution", 0) for c in per_node)
    if any("portal_crossings" in c for c in per_node):
        crossings = sum(c.get("portal_crossings", 0) for c in per_node)
        low = sum(c.get("predicted_low", 0) for c in per_node)
        out["simplified_share"] = low / crossings if crossings else None
    for prefix in ("acc_", "replay_"):
        # global counts, reported by one node: summing over nodes adds that one
        parts = [a for a in (Accuracy.from_counters(c, prefix) for c in per_node) if a]
        if not parts:
            continue
        total = sum(parts[1:], parts[0])
        if prefix == "acc_":
            out.update(acc=total.acc, acc_simplified_share=total.simplified_share,
                       acc_unrecorded_share=(total.unrecorded / total.crossings
                                             if total.crossings else None))
        else:
            out.update(replay_acc=total.acc, replay_false_low=total.false_low)
    return out
