"""Visiting order of probe targets: nearest neighbour, then 2-opt (docs/design.md §2, issue 4).

Targets are points on the object (mm). Travel between two targets goes up to the
travel height, across and down, so the cost used here is the horizontal distance
plus the vertical legs; good enough to order by, and it is what `check` reports
as the travel saved against the plan's natural order.
"""
from __future__ import annotations

import numpy as np


def travel_cost_matrix(points_mm: np.ndarray, travel_z_mm: float | None = None) -> np.ndarray:
    """Pairwise travel cost (mm): horizontal distance plus the climb to and from ``travel_z_mm``."""
    p = np.asarray(points_mm, dtype=float)
    horizontal = np.linalg.norm(p[:, None, :2] - p[None, :, :2], axis=2)
    if travel_z_mm is None:
        return np.linalg.norm(p[:, None, :] - p[None, :, :], axis=2)
    climb = np.maximum(travel_z_mm - p[:, 2], 0.0)
    cost = horizontal + climb[:, None] + climb[None, :]
    np.fill_diagonal(cost, 0.0)
    return cost


def path_cost(order: list[int] | np.ndarray, cost: np.ndarray, start: int | None = None) -> float:
    order = list(order)
    total = float(sum(cost[a, b] for a, b in zip(order, order[1:])))
    if start is not None and order:
        total += float(cost[start, order[0]])
    return total


def nearest_neighbour(cost: np.ndarray, first: int = 0) -> list[int]:
    n = cost.shape[0]
    if n == 0:
        return []
    visited = np.zeros(n, dtype=bool)
    order = [first]
    visited[first] = True
    for _ in range(n - 1):
        row = np.where(visited, np.inf, cost[order[-1]])
        nxt = int(np.argmin(row))
        order.append(nxt)
        visited[nxt] = True
    return order


def two_opt(order: list[int], cost: np.ndarray, max_passes: int = 50) -> list[int]:
    """Improve an open path by reversing segments while that shortens it (bounded passes)."""
    route = list(order)
    n = len(route)
    if n < 4:
        return route
    for _ in range(max_passes):
        improved = False
        for i in range(0, n - 2):
            a, b = route[i], route[i + 1]
            # Vectorised over all j: gain of reversing route[i+1 .. j].
            js = np.arange(i + 2, n)
            c = np.array([route[j] for j in js])
            d = np.array([route[j + 1] if j + 1 < n else -1 for j in js])
            old = cost[a, b] + np.where(d >= 0, cost[c, np.maximum(d, 0)], 0.0)
            new = cost[a, c] + np.where(d >= 0, cost[b, np.maximum(d, 0)], 0.0)
            gain = old - new
            k = int(np.argmax(gain))
            if gain[k] > 1e-9:
                j = int(js[k])
                route[i + 1:j + 1] = route[i + 1:j + 1][::-1]
                improved = True
        if not improved:
            break
    return route


def order_targets(points_mm: np.ndarray, travel_z_mm: float | None = None,
                  start_mm: np.ndarray | None = None) -> tuple[list[int], float, float]:
    """Order ``points_mm`` for short travel.

    Returns (order, cost of the natural order 0..n-1, cost of the chosen order), in mm.
    """
    p = np.asarray(points_mm, dtype=float)
    n = len(p)
    if n == 0:
        return [], 0.0, 0.0
    if start_mm is not None:
        p = np.vstack([p, np.asarray(start_mm, dtype=float)[None, :]])
    cost = travel_cost_matrix(p, travel_z_mm)
    start = n if start_mm is not None else None
    natural = list(range(n))
    first = int(np.argmin(cost[start, :n])) if start is not None else 0
    sub = cost[:n, :n]
    best = two_opt(nearest_neighbour(sub, first), sub)
    return best, path_cost(natural, cost, start), path_cost(best, cost, start)
