"""``elastoprobe status DIR [--follow]``: progress, state, faults and ETA, read-only.

Reads the journal through a read-only connection (WAL: never blocks the running
controller). ``--follow`` prints new events as they are journaled until the
session stops running (no lock holder) — bounded by the session's own life.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from .coverage import cloud_summary, describe_cloud
from .journal import Journal
from .locking import session_lock_holder


def snapshot(session_dir: Path) -> dict[str, Any]:
    """One status record of a session (JSON-able)."""
    j = Journal.open_readonly(session_dir)
    try:
        sess = j.session()
        counts = j.status_counts()
        robot = j.robot_time_s()
        transitions = j.transitions()
        faults = j.faults()
        phases = j.phases()
        cloud = j.phase("cloud", 0)
    finally:
        j.close()
    done = counts.get("done", 0)
    total = sum(counts.values())
    open_steps = counts.get("planned", 0) + counts.get("in_progress", 0) + counts.get("failed", 0)
    per_step = robot["total"] / done if done else None
    holder = session_lock_holder(session_dir)
    return {
        "session": str(session_dir),
        "plan": sess["plan_name"],
        "status": sess["status"],
        "status_reason": sess["status_reason"],
        "running_pid": holder.get("pid") if holder else None,
        "state": transitions[-1]["to_state"] if transitions else "idle",
        "phase": f"{phases[-1]['name']}[{phases[-1]['round']}]" if phases else None,
        "steps": counts,
        "steps_total": total,
        "cloud": cloud_summary(cloud.outputs) if cloud is not None else None,
        "robot_hours": round(robot["total"] / 3600.0, 4),
        "eta_robot_hours": round(per_step * open_steps / 3600.0, 3) if per_step is not None else None,
        "faults": [{"id": f.fault_id, "kind": f.kind, "step": f.step_id, "action": f.policy_action,
                    "message": f.message} for f in faults],
    }


def _print(snap: dict[str, Any]) -> None:
    s = snap["steps"]
    print(f"{snap['session']}: plan {snap['plan']!r}, {snap['status']}"
          + (f" ({snap['status_reason']})" if snap["status_reason"] else "")
          + (f", running as pid {snap['running_pid']}" if snap["running_pid"] else ""))
    print(f"  state {snap['state']}, phase {snap['phase']}")
    print(f"  steps: {s.get('done', 0)} done, {s.get('planned', 0)} planned, {s.get('in_progress', 0)} in progress, "
          f"{s.get('failed', 0)} failed (to retry), {s.get('skipped', 0)} skipped, of {snap['steps_total']}")
    if snap["cloud"] is not None:
        print(f"  cloud: {describe_cloud(snap['cloud'])}")
    eta = snap["eta_robot_hours"]
    print(f"  robot time {snap['robot_hours']:.2f} h" + (f", ETA {eta:.2f} h of robot time" if eta is not None else ""))
    if snap["faults"]:
        print(f"  faults ({len(snap['faults'])}):")
        for f in snap["faults"][-10:]:
            print(f"    #{f['id']} {f['kind']} at step {f['step']} -> {f['action']}: {f['message']}")


def show_status(session_dir: Path, follow: bool = False, as_json: bool = False, poll_s: float = 1.0) -> int:
    snap = snapshot(session_dir)
    print(json.dumps(snap)) if as_json else _print(snap)
    if not follow:
        return 0
    last_event = 0
    while True:
        j = Journal.open_readonly(session_dir)
        try:
            events = j.events(after_id=last_event)
        finally:
            j.close()
        for e in events:
            last_event = e["id"]
            line = {"t_robot_s": e["t_robot_s"], "kind": e["kind"], **e["record"]}
            print(json.dumps(line) if as_json else f"  [{e['t_wall_utc']}] {e['kind']} {e['record']}", flush=True)
        if session_lock_holder(session_dir) is None:
            final = snapshot(session_dir)
            print(json.dumps(final)) if as_json else _print(final)
            return 0
        time.sleep(poll_s)
