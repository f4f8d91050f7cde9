"""Message kinds between the coordinator and nodes (each a codec message; payload in meta)."""

HELLO = "hello"          # node -> coordinator: rank, endpoint
JOB = "job"              # coordinator -> node: store, scene, settings, peers
PROGRESS = "progress"    # node -> coordinator: paths done
HEARTBEAT = "heartbeat"  # node -> coordinator: still alive
FILM = "film"            # node -> parent node / root -> coordinator: partial film
DONE = "done"            # node -> coordinator: per-node timings and counters
STOP = "stop"            # coordinator -> node: shut down
RAYS = "rays"            # node -> node: a ray batch for the receiver's domains
ROUND = "round"          # node -> coordinator (domain): round done, batches sent per node
GO = "go"                # coordinator -> node (domain): batches to expect, or finished
STATUS = "status"        # node -> coordinator (async): idle, batches sent and received
PROBE = "probe"          # coordinator -> node (async): confirm counts, or finished
QUEUES = "queues"        # node -> coordinator (dynamic): rays waiting per domain, loaded domain
SCHEDULE = "schedule"    # coordinator -> node (dynamic): domain -> node for this round
REDUCE = "reduce"        # node -> parent node: partial of an all-reduce
BROADCAST = "bcast"      # node -> child node: result of an all-reduce

#: Kinds a node accepts (from the coordinator or from peers); anything else is dropped.
TO_NODE = frozenset({JOB, FILM, STOP, RAYS, GO, PROBE, SCHEDULE, REDUCE, BROADCAST})

#: Seconds between the coordinator's heartbeats to its nodes; a node that hears nothing from
#: the coordinator for ``COORDINATOR_SILENCE_S`` exits (the coordinator died or was cut off).
HEARTBEAT_S = 0.5
COORDINATOR_SILENCE_S = 5.0

#: Environment variable naming the coordinator's pid to the nodes it starts on its own machine:
#: they ask the kernel to kill them the moment it exits (Linux's parent-death signal).
PARENT_PID_ENV = "VASTRAY_PARENT_PID"
