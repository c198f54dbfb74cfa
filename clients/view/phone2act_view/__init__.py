"""A live Rerun view of a phone2act server: cameras, arm poses, clutch, gate and episode events.

A client of the typed API like any other (`phone2act-view --help`); see clients/view/README.md.
"""

from phone2act_view.events import EpisodeEvent, EpisodeTracker, Event, arm_events
from phone2act_view.view import View, Workspace

__all__ = ["EpisodeEvent", "EpisodeTracker", "Event", "View", "Workspace", "arm_events"]
