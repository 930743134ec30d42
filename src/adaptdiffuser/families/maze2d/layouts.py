"""Maze layouts as data: one string per row, ``#`` wall, ``.`` free cell, ``G`` the fixed evaluation goal.

The three built-in mazes are the D4RL / gymnasium-robotics Maze2D layouts; their goal cells follow Diffuser's
evaluation protocol (U-Maze (1, 1), Medium (6, 6), Large (7, 9)). Any list of strings with the same alphabet
is a valid maze.
"""

from __future__ import annotations

from dataclasses import dataclass

MAZES: dict[str, list[str]] = {
    "umaze": [
        "#####",
        "#G..#",
        "###.#",
        "#...#",
        "#####",
    ],
    "medium": [
        "########",
        "#..##..#",
        "#..#...#",
        "##...###",
        "#..#...#",
        "#.#..#.#",
        "#...#.G#",
        "########",
    ],
    "large": [
        "############",
        "#....#.....#",
        "#.##.#.#.#.#",
        "#......#...#",
        "#.####.###.#",
        "#..#.#.....#",
        "##.#.#.#.###",
        "#..#...#.G.#",
        "############",
    ],
}

# Episode lengths of Diffuser's Maze2D protocol.
EPISODE_STEPS: dict[str, int] = {"umaze": 300, "medium": 600, "large": 800}


@dataclass(frozen=True)
class Layout:
    """A parsed maze: wall grid, free cells and the evaluation goal cell (row, col)."""

    rows: tuple[str, ...]
    goal_cell: tuple[int, int] | None

    @property
    def height(self) -> int:
        return len(self.rows)

    @property
    def width(self) -> int:
        return len(self.rows[0])

    def is_free(self, row: int, col: int) -> bool:
        return 0 <= row < self.height and 0 <= col < self.width and self.rows[row][col] != "#"

    @property
    def free_cells(self) -> list[tuple[int, int]]:
        return [(r, c) for r in range(self.height) for c in range(self.width) if self.is_free(r, c)]

    def wall_map(self) -> list[list[int]]:
        """The 0/1 grid gymnasium-robotics expects (1 = wall)."""
        return [[1 if ch == "#" else 0 for ch in row] for row in self.rows]


def parse_layout(rows: list[str]) -> Layout:
    """Validate and parse a list of strings into a :class:`Layout`; raise ``ValueError`` naming the problem."""
    if not rows or not all(isinstance(r, str) for r in rows):
        raise ValueError("maze layout must be a non-empty list of strings")
    width = len(rows[0])
    if any(len(r) != width for r in rows):
        raise ValueError("maze layout rows must all have the same length")
    bad = {ch for r in rows for ch in r} - set("#.G")
    if bad:
        raise ValueError(f"maze layout has unknown characters {sorted(bad)}; use '#', '.' and 'G'")
    for r, row in enumerate(rows):
        for c, ch in enumerate(row):
            edge = r in (0, len(rows) - 1) or c in (0, width - 1)
            if edge and ch != "#":
                raise ValueError(f"maze layout must be enclosed by walls; cell ({r}, {c}) is open")
    goals = [(r, c) for r, row in enumerate(rows) for c, ch in enumerate(row) if ch == "G"]
    if len(goals) > 1:
        raise ValueError(f"maze layout has {len(goals)} 'G' cells; at most one evaluation goal is allowed")
    layout = Layout(rows=tuple(rows), goal_cell=goals[0] if goals else None)
    if len(layout.free_cells) < 2:
        raise ValueError("maze layout needs at least two free cells")
    return layout
