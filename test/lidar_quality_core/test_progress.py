from lidar_quality_core.progress import Progress


def test_counts_and_absolute_updates_write_one_line(capsys):
    bar = Progress("frames", 4)
    bar.update()
    bar.update(2, note="x")
    assert bar.done == 3
    bar(4)  # the meta_model callback form; reaching the total ends the line
    err = capsys.readouterr().err
    assert "frames [" in err and "3/4" in err and "4/4" in err
    assert err.endswith("\n") and err.count("\n") == 1
    bar.close()  # already closed: no second newline
    assert capsys.readouterr().err == ""


def test_callback_with_total_and_silent_mode(capsys):
    bar = Progress("cv", None)
    bar(1, 5)
    assert bar.total == 5
    quiet = Progress("q", 3, enabled=False)
    quiet.update(3)
    quiet.close()
    assert quiet.done == 3
    err = capsys.readouterr().err
    assert "1/5" in err and "q " not in err
