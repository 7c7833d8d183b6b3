"""A tracked hand: the hand pipeline's frames annotated by the gesture recogniser.

``TrackedHand.handle(message)`` returns output messages in order: each ``frame`` (with a
``gesture`` object: active gesture, curls, pinch and grab strength, pointing ray) followed by the
``gesture`` events it caused. Live streaming and replay both use it, so a recording replays to the
same messages. It is the one object the service holds per session: what it needs from the
pipeline (the hand, the estimator, the counters) is exposed here.
"""
from __future__ import annotations

from typing import Iterable, Iterator

from gestures.recognizer import GestureRecognizer, GestureSettings

from ..estimators.registry import EstimatorSpec
from ..protocol.outgoing import FrameDict, GestureDict

from .frame_text import FrameOutput, Layouts
from .hand import Counters, Dropped, HandSession, PipelineSettings


class TrackedHand:
    def __init__(self, hand: str = "right", settings: PipelineSettings | None = None,
                 gesture_settings: GestureSettings | None = None):
        self._session = HandSession(hand, settings)
        self.recognizer = GestureRecognizer(gesture_settings or GestureSettings())
        self._layouts = Layouts()           # the fixed parts of this hand's frames' text (``FrameOutput``)
        # the session's own methods for the two called per message (no call of this class's around them)
        self.accept = self._session.accept
        self.tick_ready = self._session.tick_ready

    @property
    def hand(self) -> str:
        """``right`` or ``left`` (a source's ``hello`` may change it)."""
        return self._session.hand

    @property
    def estimator_name(self) -> str:
        return self._session.estimator_name

    @property
    def counters(self) -> Counters:
        """The pipeline's running counts of dropped input, clock steps and reference poses."""
        self._session.flush()
        return self._session.counters

    def set_estimator(self, spec: EstimatorSpec | str, params: dict | None = None) -> None:
        """Switch every finger's estimator live (``HandSession.set_estimator``)."""
        self._session.set_estimator(spec, params)

    def set_gesture_settings(self, settings: GestureSettings) -> None:
        self.recognizer.settings = settings

    def handle(self, message) -> list[FrameDict | GestureDict]:
        return [m for group in self.handle_iter(message) for m in group]

    def handle_iter(self, message) -> Iterator[list[FrameDict | GestureDict]]:
        """For each frame the message completes, as soon as it is ready: the frame and its events."""
        self.accept(message)
        yield from self.outputs()

    def accept(self, message) -> Dropped:
        """Take one source message in; returns what it dropped and why. Its outputs follow from
        ``outputs``. (Each instance has ``HandSession.accept`` itself in its place.)"""
        return self._session.accept(message)

    def tick_ready(self) -> bool:
        """Whether ``outputs`` would process another tick now (then the outputs so far have later work
        behind them). (Each instance has ``HandSession.tick_ready`` itself in its place.)"""
        return self._session.tick_ready()

    def ticks_ready(self, count: int) -> bool:
        """Whether ``outputs`` would process at least ``count`` more ticks now (``HandSession.ticks_ready``)."""
        return self._session.ticks_ready(count)

    def next_frame_covered(self) -> bool:
        """Whether the next frame's tick waits only for the reorder window (``HandSession.next_frame_covered``)."""
        return self._session.next_frame_covered()

    def outputs(self) -> Iterator[list[FrameDict | GestureDict]]:
        """For each frame that is ready, as soon as it is: the frame message and its gesture events."""
        for out, events in self.frame_outputs():
            yield [out.message(), *events]

    def frame_outputs(self) -> Iterator[tuple[FrameOutput, list[GestureDict]]]:
        """``outputs`` with each frame as a ``FrameOutput`` (its message built only when asked; its JSON text
        written from the frame's arrays)."""
        for frame in self._session.ready_frames():
            annotation, events = self.recognizer.update(frame)
            yield FrameOutput(frame, self._session.calibration, annotation, self._layouts), events


def replay(messages: Iterable, settings: PipelineSettings | None = None,
           gesture_settings: GestureSettings | None = None, hand: str = "right") -> Iterator[FrameDict | GestureDict]:
    """Every output message of a sequence of parsed source messages."""
    tracked = TrackedHand(hand, settings, gesture_settings)
    for msg in messages:
        yield from tracked.handle(msg)
