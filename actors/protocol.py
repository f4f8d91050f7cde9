"""Message kinds between the coordinator and nodes (each a codec message; payload in meta)."""

HELLO = "hello"          # node -> coordinator: rank, endpoint
JOB = "job"              # coordinator -> node: store, scene, settings, peers
PROGRESS = "progress"    # node -> coordinator: paths done
HEARTBEAT = "heartbeat"  # node -> coordinator: still alive
FILM = "film"            # node -> parent node / root -> coordinator: partial film
DONE = "done"            # node -> coordinator: per-node timings and counters
STOP = "stop"            # coordinator -> node: shut down
