"""Progress for long work (dqm.progress): the elapsed-time ticker of calls that report no counts."""
import io
import threading
import time

import pytest

from dqm.progress import ProgressBar, Ticker, ticking


class Terminal(io.StringIO):
    """A stream that says it is a terminal."""

    def isatty(self) -> bool:
        return True


def tickers() -> list:
    return [t for t in threading.enumerate() if t.name == "dqm-ticker"]


def test_ticker_redraws_its_label_and_elapsed_time_and_its_thread_ends_with_the_block():
    stream = Terminal()
    with Ticker("mapping (COLMAP's global mapper)", stream=stream, every=0.05):
        assert len(tickers()) == 1
        time.sleep(1.2)
    text = stream.getvalue()
    assert "mapping (COLMAP's global mapper): 00:00 elapsed" in text
    assert "mapping (COLMAP's global mapper): 00:01 elapsed" in text  # redrawn while the block ran
    assert text.count("\r") >= 5 and not tickers()


def test_ticker_stops_when_the_block_raises():
    stream = Terminal()
    with pytest.raises(KeyboardInterrupt):
        with Ticker("bundle adjustment", stream=stream, every=0.05):
            raise KeyboardInterrupt
    assert "bundle adjustment: 00:00 elapsed" in stream.getvalue() and not tickers()


def test_ticker_is_silent_when_piped_or_asked_to_be():
    for stream, force in ((io.StringIO(), None), (Terminal(), False)):
        with Ticker("triangulation", stream=stream, force=force, every=0.01):
            time.sleep(0.05)
            assert not tickers()
        assert stream.getvalue() == ""


def test_ticking_shows_a_ticker_only_for_a_terminals_progress():
    assert isinstance(ticking(True, "x"), Ticker)
    stream = Terminal()
    with ticking(ProgressBar("sift", stream=stream), "sift (COLMAP's extractor)") as t:
        assert isinstance(t, Ticker)
    assert "sift (COLMAP's extractor): 00:00 elapsed" in stream.getvalue()
    for progress in (None, False, ProgressBar("x"), lambda done, total: None):
        with ticking(progress, "x") as t:
            assert t is None
