"""The flight log's topic names and metadata record name: the one place the recorder (writer) and
the log reader agree on, so that reading a log imports neither foxglove nor MAVSDK."""

from __future__ import annotations

TOPIC_DEPTH = "/camera/depth"
TOPIC_GRAY = "/camera/gray"
TOPIC_STATE = "/vehicle/state"
TOPIC_OBSERVATION = "/policy/observation"
TOPIC_ACTION = "/policy/action"
TOPIC_COMMAND = "/vehicle/command"
TOPIC_LATENT = "/policy/latent"
TOPIC_TIMING = "/timing"
TOPIC_WATCHDOG = "/watchdog"
TOPIC_STATUS_TEXT = "/vehicle/status_text"
CAMERA_FRAME_ID = "camera"
# The metadata record (written before the first message) that carries the log's clock offset.
METADATA_NAME = "cmnav"

# The camera frames, and the policy step's recorded inputs and outputs, as readers group them.
FRAME_TOPICS = (TOPIC_DEPTH, TOPIC_GRAY)
STEP_TOPICS = (TOPIC_OBSERVATION, TOPIC_ACTION)
