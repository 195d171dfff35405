"""Recording and replay: MCAP files of a robot's decisions and data (docs/recording.md).

- :class:`Recorder` taps blackboards, event buses, HAL commands and ROS 2 topics into an
  MCAP file without ever blocking them (a bounded queue per channel, counted drops).
- :func:`read_recording` reads a recording back, also one cut short by a crash.
- :func:`replay` runs a robot's logics and behaviours on a recording: its HALs replaced
  by a replay source, its behaviours fed the recorded topics, every command captured;
  :func:`compare` finds the first divergence.
- ``beehave replay | inspect | plot`` on the command line (:mod:`beehave.recording.cli`).
"""

from beehave.errors import RecordingError
from beehave.recording.reader import Recorded, Recording, decode_ros, read_recording
from beehave.recording.recorder import DEFAULT_TOPICS, STANDARD_TOPICS, Recorder, command_methods
from beehave.recording.writer import RecorderStats, recording_files

__all__ = ["DEFAULT_TOPICS", "STANDARD_TOPICS", "Recorded", "Recorder", "RecorderStats",
           "Recording", "RecordingError", "command_methods", "decode_ros", "read_recording",
           "recording_files"]
