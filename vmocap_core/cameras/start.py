"""When a recorded source starts playing: once its readers are there.

Frames published before a reader has matched are lost to it (images are volatile), and in
lockstep one lost frame stalls the graph for lockstep_timeout_ms. So a replay starts
SETTLE_S after every image topic has a reader and every waited-for topic has one (the pause
lets a reader's other topics match too); a reader of only some cameras gets them
PARTIAL_MATCH_S after it matched; and it starts anyway `wait_s` after start-up.
"""

from __future__ import annotations

from typing import Sequence

SETTLE_S = 0.2
PARTIAL_MATCH_S = 2.0


class StartGate:
    """Feed it what has readers (`update`, on a timer); it answers with the log note of the start
    ("" when every image topic has a reader) once the replay may begin, None until then."""

    def __init__(self, now: float, wait_s: float) -> None:
        self.deadline = now + wait_s
        self.first_match: float | None = None  # some image topic (and every waited-for topic) has a reader
        self.all_matched: float | None = None  # every image topic has one

    def update(self, now: float, matched: Sequence[bool], waited: bool) -> str | None:
        """matched: per image topic, has it a reader; waited: has every waited-for topic one."""
        if self.first_match is None and any(matched) and waited:
            self.first_match = now
        if self.all_matched is None and all(matched) and waited:
            self.all_matched = now
        if not ((self.all_matched is not None and now >= self.all_matched + SETTLE_S)
                or (self.first_match is not None and now >= self.first_match + PARTIAL_MATCH_S) or now >= self.deadline):
            return None
        if self.first_match is None:
            return " (no subscriber yet)"
        return "" if all(matched) else f" (subscribers on {sum(matched)} of {len(matched)} image topics)"
