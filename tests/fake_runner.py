"""A base for the fake flight runners of the evaluation tests."""

from __future__ import annotations


class SequentialTrials:
    """``Runner.fly_trials`` of a fake runner: its ``fly`` for each seed, in order."""

    def fly_trials(self, method, scenario, seeds, estimated=False, compensate_delay=False):
        return [self.fly(method, scenario, s, estimated, compensate_delay) for s in seeds]
