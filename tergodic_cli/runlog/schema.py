"""The layout of a tergodic run log: topics, schema names, metadata names, version.

One place names everything the writer emits and the reader expects, so the two
cannot drift apart. Bump :data:`LOG_SCHEMA_VERSION` whenever a topic changes
meaning or a field the reader relies on changes shape; the reader refuses logs
of any version it does not list in :data:`SUPPORTED_VERSIONS`.
"""

from __future__ import annotations

#: Version of the log layout, stored in metadata ``tergodic`` as ``log_schema_version``.
# 3: log times are the wall clock when each message was written; the simulated time is in the messages
#    (stamps = metadata ``time_origin_ns`` + t, records' t); /robot/sample and /robot/wrench are protobuf.
# 2: log times were ``time_origin_ns`` + simulated t (stamps the same); /robot/sample, /robot/wrench JSON.
# 1: log times and stamps were simulated t from 0. The reader reads all three.
LOG_SCHEMA_VERSION = "3"
SUPPORTED_VERSIONS = ("1", "2", "3")

#: MCAP profile string in the header ("" = no ROS profile; every message is protobuf).
PROFILE = ""

# Frames. Agent positions, normals and the cloud are in the capture's frame; the
# robot quantities are in the robot base frame (CONTRACTS.md, robot_sample_dict).
FRAME_OBJECT = "object"
FRAME_BASE = "base"
FRAME_EE = "ee"

# --- topics --------------------------------------------------------------------------------
# Every step.
TOPIC_METRICS = "/explorer/metrics"          # tergodic.StepRecord (protobuf, proto.py): step, t, ergodicity,
                                             #   residual_ref, touched_fraction, step_ms, positions, velocities,
                                             #   normals, as float64 (exact)
TOPIC_AGENT_POSES = "/explorer/agent_poses"  # foxglove.PosesInFrame, one pose per agent (z = surface normal, x = heading)
TOPIC_AGENT_SCENE = "/explorer/agent_scene"  # foxglove.SceneUpdate: normal line L_a⊥ and velocity arrow per agent
# Every step, robot runs only.
TOPIC_ROBOT_SAMPLE = "/robot/sample"         # tergodic.RobotSample (protobuf, proto.py): the robot sample dict
                                             #   exactly as the robot produced it (JSON before version 3)
TOPIC_EE_POSE = "/robot/ee_pose"             # foxglove.PoseInFrame in the base frame
TOPIC_TF = "/tf"                             # foxglove.FrameTransform, one message per link (+ ee, + object when known)
TOPIC_JOINTS = "/robot/joint_states"         # foxglove.JointStates: q, dq, tau
TOPIC_WRENCH = "/robot/wrench"               # tergodic.Wrench (protobuf, proto.py): measured and desired wrench
                                             #   with named components (JSON before version 3)
TOPIC_WRENCH_SCENE = "/robot/wrench_scene"   # foxglove.SceneUpdate: measured and desired force arrows at the tool
# Robot runs, whenever the robot's state changes / every window of 1 kHz ticks (protobuf, proto.py).
TOPIC_ROBOT_PHASE = "/robot/phase"           # tergodic.RobotPhase: step, t, source, target, reason
TOPIC_ROBOT_FORCE = "/robot/force"           # tergodic.ForceWindow: state, t_start, t_end, ticks, force_max,
                                             #   force_mean (|f| over the window's ticks) + the cumulative tick figures
# Every K steps and at the end.
TOPIC_CLOUD = "/cloud"                       # foxglove.PointCloud: x y z + target coverage heat source (float32)
# Whenever something happens.
TOPIC_EVENTS = "/events"                     # foxglove.Log: "step N: text"

# --- metadata records (MCAP metadata is a map<string, string>) --------------------------------
META_TERGODIC = "tergodic"    # log_schema_version, writer, frames, cloud_every, n_points, n_agents
META_CONFIG = "config"        # {"json": <the run config as JSON>}
META_SEED = "seed"            # {"seed": "<int>"}
META_VERSIONS = "versions"    # library versions, one key per library
META_SUMMARY = "summary"      # written by close(summary): {"json": <summary.json as JSON>}
META_END = "end"              # written by close(): steps, clouds, status
ATTACHMENT_SIDECAR = "capture.json"

#: Float fields of every PointCloud point after x, y, z, in order (all float32).
CLOUD_FIELDS = ("target", "coverage", "heat", "source")
