"""Deprecated path of `pyrtu.outbox.report`: each of its names warns, naming the new path."""

from pyrtu.core._deprecated import moved
from pyrtu.outbox import report as moved_to

__getattr__ = moved(__name__, moved_to.__name__, moved_to.__all__)
