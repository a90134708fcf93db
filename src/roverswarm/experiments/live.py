"""The live table of a grid's runs: done, running and left, and the estimated time left."""

from __future__ import annotations

import time

from rich.table import Table

from roverswarm.experiments.arms import GridRun, episodes_done


class Summary:
    """A rich table of the grid: runs done, running and left, and the estimated time left."""

    def __init__(self, runs: list[GridRun], done: set[str]):
        self.runs = runs
        self.done = set(done)
        # as saved: a partial run starts there, a done one may have ended early (a budget)
        self.saved = {r.name: episodes_done(r) for r in runs}
        self.running: dict[str, int] = {}
        self.started = time.perf_counter()
        self.trained = 0  # seed-episodes trained by this command (for the time estimate)

    def progress(self, run: GridRun, episodes: int) -> None:
        previous = self.running.get(run.name, episodes)
        self.trained += max(episodes - previous, 0) * run.config.seeds
        self.running[run.name] = episodes

    def finish(self, run: GridRun) -> None:
        self.running.pop(run.name, None)
        self.done.add(run.name)
        self.saved[run.name] = episodes_done(run)

    def _at(self, run: GridRun) -> int:
        """Episodes per seed a run stands at: as it reported while running, else as saved."""
        return self.running.get(run.name, self.saved[run.name])

    def __rich__(self) -> Table:
        left = [r for r in self.runs if r.name not in self.done]
        todo = sum((r.config.episodes - self._at(r)) * r.config.seeds for r in left)
        elapsed = time.perf_counter() - self.started
        eta = f"{todo * elapsed / self.trained / 60:.0f} min" if self.trained else "-"
        head = (
            f"runs: {len(self.done)} done, {len(self.running)} running, "
            f"{len(left) - len(self.running)} left; time left ~ {eta}"
        )
        table = Table(title=head, title_justify="left")
        for column in ("run", "state", "episodes"):
            table.add_column(column)
        for r in self.runs:
            state = "done" if r.name in self.done else ("running" if r.name in self.running else "queued")
            episodes = self._at(r)
            table.add_row(r.name, state, f"{episodes}/{r.config.episodes}")
        return table
