"""Vehicle poses on the world's road network (world frame: metres, yaw CCW from east).

The roads (:class:`roads.Road`, world centrelines) are cut at junctions (vertices shared by
several roads, which OSM ways share exactly) into edges; each edge becomes one or two directed
arcs as ``oneway`` allows. Vehicles drive right-hand traffic in a lane of the arc, heading
along the road with small noise. Everything is a pure function of the ``rng`` passed in.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import shapely

from seglocnet_jax.geometry import wrap_angle


@dataclasses.dataclass(frozen=True)
class Arc:
    """A directed drivable edge: ``points`` (M, 2) world metres in travel direction."""

    points: np.ndarray
    cum: np.ndarray  # (M,) arc length at each vertex
    start: int  # node ids
    end: int
    edge: int  # undirected edge id (an arc and its reverse share it)
    offsets: tuple[float, ...]  # lane centre offsets to the right of travel, metres


@dataclasses.dataclass(frozen=True)
class RoadGraph:
    arcs: list[Arc]
    out: dict[int, list[int]]  # node -> outgoing arc indices
    weights: np.ndarray  # (A,) arc lengths, for uniform sampling over the network


def _lane_offsets(road) -> tuple[float, ...]:
    """Lane centres (metres right of the travel direction) of one direction of ``road``."""
    if road.oneway:
        lane_w = road.width / road.lanes
        return tuple(road.width / 2 - (j + 0.5) * lane_w for j in range(road.lanes))
    lane_w = road.width / max(road.lanes, 2)
    return tuple((j + 0.5) * lane_w for j in range(max(1, road.lanes // 2)))


def build_graph(roads) -> RoadGraph:
    """The directed road graph of ``roads`` (one-way roads only along their centreline)."""
    keys = [np.round(r.centerline * 100).astype(np.int64) for r in roads]
    count: dict[tuple, int] = {}
    for k in keys:
        for v in {tuple(p) for p in k}:
            count[v] = count.get(v, 0) + 1
    node_id: dict[tuple, int] = {}
    arcs: list[Arc] = []
    edge = 0
    for road, k in zip(roads, keys, strict=True):
        cut = [i for i in range(len(k)) if i in (0, len(k) - 1) or count[tuple(k[i])] > 1]
        for a, b in zip(cut[:-1], cut[1:], strict=True):
            pts = road.centerline[a : b + 1]
            u = node_id.setdefault(tuple(k[a]), len(node_id))
            v = node_id.setdefault(tuple(k[b]), len(node_id))
            seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
            if seg.sum() < 0.5:
                continue
            lanes = _lane_offsets(road)
            arcs.append(Arc(pts, np.concatenate([[0.0], np.cumsum(seg)]), u, v, edge, lanes))
            if not road.oneway:
                rev_cum = np.concatenate([[0.0], np.cumsum(seg[::-1])])
                arcs.append(Arc(pts[::-1], rev_cum, v, u, edge, lanes))
            edge += 1
    out: dict[int, list[int]] = {}
    for i, arc in enumerate(arcs):
        out.setdefault(arc.start, []).append(i)
    return RoadGraph(arcs, out, np.array([a.cum[-1] for a in arcs]))


def graph_of(world) -> RoadGraph:
    """The world's road graph (built on first use, kept on ``world.graph``)."""
    if world.graph is None:
        world.graph = build_graph(world.roads)
    return world.graph


def pose_on_arc(arc: Arc, s, offset):
    """World poses ``(n, 3)`` at arc lengths ``s`` (n,) and right offsets ``offset`` (n,)."""
    s = np.clip(np.asarray(s, np.float64), 0, arc.cum[-1])
    k = np.clip(np.searchsorted(arc.cum, s, side="right") - 1, 0, len(arc.points) - 2)
    seg = arc.points[k + 1] - arc.points[k]
    length = np.maximum(np.linalg.norm(seg, axis=1), 1e-9)
    t = seg / length[:, None]
    p = arc.points[k] + ((s - arc.cum[k]) / length)[:, None] * seg
    right = np.stack([t[:, 1], -t[:, 0]], axis=1)
    xy = p + np.asarray(offset)[:, None] * right
    return np.column_stack([xy, np.arctan2(t[:, 1], t[:, 0])])


def _inside(poses: np.ndarray, region) -> np.ndarray:
    if region is None:
        return np.ones(len(poses), bool)
    return shapely.contains_xy(region, poses[:, 0], poses[:, 1])


# Nominal speed (m/s, 36 km/h) that turns the distance along a route into simulated time: a
# frame's ``timestamp`` is its distance from the route's first frame divided by it.
NOMINAL_SPEED_MPS = 10.0


@dataclasses.dataclass(frozen=True)
class Trajectory:
    """Frames along routes (world metres / radians).

    Attributes:
      poses: ``(n, 3)`` world x, y (m), yaw (rad).
      route: ``(n,)`` int64 route number of each frame (0-based, in the order routes were
        driven; a route whose frames all fell outside the region leaves its number unused).
      index: ``(n,)`` int64 index of the frame along its route (0 = the route's first frame;
        gaps where frames were dropped by a region).
      spacing_m: metres between consecutive frames of a route (along the lane's centreline).
    """

    poses: np.ndarray
    route: np.ndarray
    index: np.ndarray
    spacing_m: float

    @property
    def distance(self) -> np.ndarray:
        """``(n,)`` metres along the route from its first frame."""
        return self.index * float(self.spacing_m)

    @property
    def timestamps(self) -> np.ndarray:
        """``(n,)`` seconds since the route's first frame at :data:`NOMINAL_SPEED_MPS`."""
        return self.distance / NOMINAL_SPEED_MPS

    def __len__(self) -> int:
        return len(self.poses)


def _walk(graph, rng, a, s, lane, want, spacing_m, lateral_noise, yaw_noise_deg):
    """Frames ``(m, 3)`` from arc ``a`` at arc length ``s``, in lane ``lane``: at least
    ``want`` unless stuck, possibly more (the piece count bounds the loop and each piece is
    capped by ``want`` minus the pieces so far: drive()'s historical behaviour, kept so that its
    frames stay bit-identical).

    A frame every ``spacing_m`` metres along the arcs; at a junction a random outgoing arc other
    than the reverse of the current edge; at a dead end of a two-way road the reverse arc (a
    U-turn into the other lane); where no arc leaves (a one-way road's dead end) the walk ends
    early. Random numbers per arc piece: lateral then yaw noise (n normals each); per junction
    one integer. ``drive`` and ``route`` share it, so drive()'s draws are as they always were.
    """
    poses = []
    while len(poses) < want:
        arc = graph.arcs[a]
        if s <= arc.cum[-1]:
            n = int(np.floor((arc.cum[-1] - s) / spacing_m)) + 1
            n = min(n, want - len(poses))
            st = s + spacing_m * np.arange(n)
            off = arc.offsets[lane % len(arc.offsets)]
            lat = off + lateral_noise * rng.standard_normal(n)
            p = pose_on_arc(arc, st, lat)
            p[:, 2] = wrap_angle(p[:, 2] + np.radians(yaw_noise_deg) * rng.standard_normal(n))
            poses.append(p)
            s = st[-1] + spacing_m
            if sum(len(q) for q in poses) >= want:
                break
        s -= arc.cum[-1]
        nxt = [j for j in graph.out.get(arc.end, []) if graph.arcs[j].edge != arc.edge]
        if not nxt:
            nxt = graph.out.get(arc.end, [])  # dead end: the reverse arc, if the road is two-way
        if not nxt:
            break  # stuck: a one-way road ends here
        a = int(nxt[rng.integers(len(nxt))])
    return np.concatenate(poses) if poses else np.zeros((0, 3))


def _start(graph, rng):
    """A uniformly random point of the network and a lane: ``(arc, arc length, lane)``."""
    a = int(rng.choice(len(graph.arcs), p=graph.weights / graph.weights.sum()))
    s = rng.uniform(0, graph.arcs[a].cum[-1])
    lane = int(rng.integers(0, 8))
    return a, s, lane


def _checked_graph(world, spacing_m: float, what: str) -> RoadGraph:
    graph = graph_of(world)
    if spacing_m <= 0:
        raise ValueError(f"{what}: spacing_m={spacing_m}, expected > 0")
    if graph.weights.sum() <= 0:
        raise ValueError(f"world {world.name!r}: the road graph has no drivable length")
    return graph


def drive_routes(
    world,
    rng: np.random.Generator,
    num_frames: int,
    spacing_m: float = 4.0,
    *,
    route_frames: tuple[int, int] = (10, 60),
    lateral_noise: float = 0.15,
    yaw_noise_deg: float = 1.0,
    region=None,
) -> Trajectory:
    """``num_frames`` frames of many short random routes on the world's road network.

    Each route starts at a uniformly random point of the network, keeps a random lane, takes a
    random turn at every junction (no U-turns unless at a dead end; one-way arcs only forward)
    and emits a frame every ``spacing_m`` metres for ``route_frames`` (min, max) frames.
    ``region`` (shapely, world metres): keep only frames inside it (routes still run outside).
    Deterministic for a given ``rng`` state; the poses are :func:`drive`'s.
    """
    if num_frames <= 0:
        graph_of(world)
        empty = np.zeros((0,), np.int64)
        return Trajectory(np.zeros((0, 3)), empty, empty.copy(), float(spacing_m))
    graph = _checked_graph(world, spacing_m, "drive")
    out, route_ids, index = [], [], []
    have, routes = 0, 0
    while have < num_frames:
        routes += 1
        if routes > 100 * num_frames + 1000:
            raise ValueError(f"drive: region holds too little road to find {num_frames} frames")
        want = int(rng.integers(route_frames[0], route_frames[1] + 1))
        a, s, lane = _start(graph, rng)
        frames = _walk(graph, rng, a, s, lane, want, spacing_m, lateral_noise, yaw_noise_deg)
        if len(frames):
            keep = _inside(frames, region)
            out.append(frames[keep])
            route_ids.append(np.full(int(keep.sum()), routes - 1, np.int64))
            index.append(np.flatnonzero(keep).astype(np.int64))
            have += int(keep.sum())
    return Trajectory(
        np.concatenate(out)[:num_frames],
        np.concatenate(route_ids)[:num_frames],
        np.concatenate(index)[:num_frames],
        float(spacing_m),
    )


def drive(world, rng: np.random.Generator, num_frames: int, spacing_m: float = 4.0, **kw):
    """Poses ``(num_frames, 3)`` of many random routes on the world's road network: the poses
    of :func:`drive_routes` (same arguments, same random draws)."""
    return drive_routes(world, rng, num_frames, spacing_m, **kw).poses


def route(
    world,
    rng: np.random.Generator,
    length_m: float,
    spacing_m: float = 5.0,
    *,
    lateral_noise: float = 0.15,
    yaw_noise_deg: float = 1.0,
) -> Trajectory:
    """One continuous drive of ``length_m`` metres (``floor(length_m / spacing_m) + 1`` frames,
    a frame every ``spacing_m`` metres) from a uniformly random point of the network.

    The car keeps a random lane and takes a random turn at every junction (never back the way it
    came; one-way arcs only forward). At the dead end of a two-way road it turns back (a U-turn
    into the opposite lane: consecutive frames there are up to a road width further apart than
    ``spacing_m``). Where no arc leaves (a one-way road that ends, e.g. clipped at the map's
    edge) the drive is stuck and ends early: the trajectory is then shorter (callers that need
    the full length draw another start). Frames never jump: each is ``spacing_m`` along the
    lane centreline from the previous one. Deterministic for the ``rng`` state.
    """
    graph = _checked_graph(world, spacing_m, "route")
    if not length_m >= 0:
        raise ValueError(f"route: length_m={length_m}, expected >= 0")
    want = int(np.floor(length_m / spacing_m + 1e-9)) + 1
    a, s, lane = _start(graph, rng)
    poses = _walk(graph, rng, a, s, lane, want, spacing_m, lateral_noise, yaw_noise_deg)
    poses = poses[:want]  # the walk's last arc piece may overshoot (drive() keeps its frames)
    n = len(poses)
    return Trajectory(poses, np.zeros(n, np.int64), np.arange(n, dtype=np.int64), float(spacing_m))


def sample_poses(
    world,
    rng: np.random.Generator,
    num: int,
    *,
    region=None,
    lateral_noise: float = 0.15,
    yaw_noise_deg: float = 1.0,
) -> np.ndarray:
    """Independent poses ``(num, 3)`` uniformly over the lanes of the network (inside
    ``region`` if given, by rejection)."""
    graph = graph_of(world)
    p = graph.weights / graph.weights.sum()
    out, tries = [], 0
    while sum(len(o) for o in out) < num:
        tries += 1
        if tries > 1000:
            raise ValueError(f"sample_poses: region holds too little road for {num} poses")
        arcs = rng.choice(len(graph.arcs), size=max(num, 64), p=p)
        batch = []
        for a in arcs:
            arc = graph.arcs[a]
            off = arc.offsets[rng.integers(len(arc.offsets))] + lateral_noise * rng.normal()
            pose = pose_on_arc(arc, [rng.uniform(0, arc.cum[-1])], [off])[0]
            pose[2] = wrap_angle(pose[2] + np.radians(yaw_noise_deg) * rng.normal())
            batch.append(pose)
        batch = np.array(batch)
        out.append(batch[_inside(batch, region)])
    return np.concatenate(out)[:num]


def lane_poses(world, spacing_m: float = 4.0, *, region=None) -> np.ndarray:
    """Every ``spacing_m`` metres along the rightmost lane of every arc: a deterministic
    enumeration ``(n, 3)`` of the network's poses (inside ``region`` if given)."""
    out = []
    for arc in graph_of(world).arcs:
        st = np.arange(0.0, arc.cum[-1], spacing_m)
        out.append(pose_on_arc(arc, st, np.full(len(st), arc.offsets[0])))
    poses = np.concatenate(out) if out else np.zeros((0, 3))
    return poses[_inside(poses, region)]
