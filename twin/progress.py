"""Progress bars that read well in a terminal and stay quiet in a log: tqdm's, drawn only when the stream is a
terminal (tqdm's disable=None), so that a CI log or a redirected run does not fill with one line per update. Every
command's --no-progress turns them off everywhere."""
from __future__ import annotations


def progress_bar(iterable=None, *, enabled: bool = True, **kwargs):
    """tqdm(iterable, **kwargs) on a terminal when `enabled`; a silent one (the same object, nothing drawn) otherwise."""
    from tqdm import tqdm

    return tqdm(iterable, disable=None if enabled else True, **kwargs)
