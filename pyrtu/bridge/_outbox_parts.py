"""Deprecated path of `pyrtu.outbox._parts`: each of its names warns, naming the new path."""

from pyrtu.core._deprecated import moved
from pyrtu.outbox import _parts as moved_to

__getattr__ = moved(__name__, moved_to.__name__, moved_to.__all__)
