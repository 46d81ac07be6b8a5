"""Recordings: MCAP files with Foxglove's schemas (writing, replaying) and ROS 2 bags.

See docs/FORMATS.md ("Recordings") for the file layout and the topic-map format.
"""

from trifuse.app.recording.errors import RecordingDamaged, RecordingError, TopicMapError
from trifuse.app.recording.reader import ReplaySource
from trifuse.app.recording.ros2 import Ros2BagSource
from trifuse.app.recording.topicmap import TopicMap, load_topic_map
from trifuse.app.recording.writer import RecordingWriter

__all__ = [
    "RecordingDamaged",
    "RecordingError",
    "RecordingWriter",
    "ReplaySource",
    "Ros2BagSource",
    "TopicMap",
    "TopicMapError",
    "load_topic_map",
]
