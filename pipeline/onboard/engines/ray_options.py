"""How the Ray engine lays the onboarding stages out on a cluster (``OnboardConfig.ray``).

None of this changes what is written (no fingerprint depends on it), only where and how fast it runs.
Defaults fit a single machine; ``docs/scaling.md`` explains how to size them for a cluster.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RayOptions:
    """Cluster address, actor pool sizes, batch sizes and fault tolerance of ``--engine ray``."""

    #: None: start a local Ray instance in this process; "auto": the cluster this machine belongs to;
    #: "ray://HEAD:10001": a remote cluster through Ray Client.
    address: str | None = None
    #: CPUs of a local instance (None: every core). Ignored when joining a cluster.
    num_cpus: int | None = None
    #: Render actors, each one CPU worker holding one GL context in a child process (0: one per CPU
    #: left after the model actors, at most one per mesh to render).
    render_workers: int = 0
    #: Meshes per render task; a crashed task is retried as a whole, so keep it small.
    render_batch_size: int = 2
    #: Captioner actors (each holds one captioning model).
    caption_actors: int = 1
    #: Actors per encoder (text encoder, and each image encoder role).
    embed_actors: int = 1
    #: Meshes per captioning batch (8 views each).
    caption_batch_size: int = 8
    #: Meshes per embedding batch.
    embed_batch_size: int = 16
    #: GPUs per model actor (None: share the cluster's GPUs evenly among the model actors, at most 1
    #: each; 0 on a CPU-only cluster).
    gpus_per_actor: float | None = None
    #: CPUs reserved per model actor (None: 1 with GPUs, 0.25 without, so render keeps the cores).
    model_actor_cpus: float | None = None
    #: Times a mesh lost with a node (an infrastructure failure, never counted against the mesh) is
    #: re-submitted before the run stops with an error; a mesh that kills a fresh worker twice with no
    #: node lost is an ``errors`` row (WorkerCrash) instead.
    max_retries: int = 3
    #: seconds a round may go without a batch, after a node was lost in it, while an actor of the run
    #: waits to be placed: Ray Data then restarts the lost actors with the layout planned for the old
    #: cluster and can wait for ever for room the survivors lack; the round is abandoned (the driver
    #: reconnects, which ends its actors) and the rest is planned again on the nodes alive
    stall_s: float = 120.0
    #: seconds a round may go without a batch once any node of the run was lost, even with every actor
    #: placed (None: 5 x ``stall_s``): a safety net for a round that waits on a lost node in a way Ray
    #: does not show as a waiting actor; the round is abandoned and redone as after ``stall_s``
    stall_placed_s: float | None = None
    #: Testing only: "STAGE:MESH_ID_PREFIX:MARKER_FILE" kills the STAGE actor (render, caption,
    #: embed_text, embed_image) once, on the batch holding that mesh, if MARKER_FILE does not exist yet
    #: (it is created first); "STAGE:MESH_ID_PREFIX:" kills it on every attempt.
    inject_fault: str = ""
    #: Testing only: "STAGE:MESH_ID_PREFIX:MARKER_FILE" makes the STAGE actor, on the first batch
    #: holding that mesh, write its Ray node id to MARKER_FILE and wait there (for the test to kill
    #: the node); later attempts run normally.
    pause_at: str = ""
