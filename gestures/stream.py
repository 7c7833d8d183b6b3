"""A tracked hand: the hand pipeline's frames annotated by the gesture recogniser.

``TrackedHand.handle(message)`` returns output messages in order: each ``frame`` (with a
``gesture`` object: active gesture, curls, pinch and grab strength, pointing ray) followed by the
``gesture`` events it caused. Live streaming and replay both use it, so a recording replays to the
same messages.
"""
from __future__ import annotations

from typing import Iterable, Iterator

from service.pipeline.hand import HandSession, PipelineSettings

from .recognizer import GestureRecognizer, GestureSettings


class TrackedHand:
    def __init__(self, hand: str = "right", settings: PipelineSettings | None = None,
                 gesture_settings: GestureSettings | None = None):
        self.session = HandSession(hand, settings)
        self.recognizer = GestureRecognizer(gesture_settings or GestureSettings())

    def set_gesture_settings(self, settings: GestureSettings) -> None:
        self.recognizer.settings = settings

    def handle(self, message) -> list[dict]:
        return [m for group in self.handle_iter(message) for m in group]

    def handle_iter(self, message) -> Iterator[list[dict]]:
        """For each frame the message completes, as soon as it is ready: the frame and its events."""
        for frame in self.session.handle_iter(message):
            annotation, events = self.recognizer.update(frame)
            msg = frame.to_message(self.session.calibration)
            msg["gesture"] = annotation
            yield [msg, *events]


def replay(messages: Iterable, settings: PipelineSettings | None = None,
           gesture_settings: GestureSettings | None = None, hand: str = "right") -> Iterator[dict]:
    """Every output message of a sequence of parsed source messages."""
    tracked = TrackedHand(hand, settings, gesture_settings)
    for msg in messages:
        yield from tracked.handle(msg)
