"""``main()`` helper for the node executables: init, spin, orderly exit on SIGINT / SIGTERM."""
from __future__ import annotations

import gc
import signal
import sys
import threading
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

from .executors import SubmitOnceExecutor
from .threads import keep_freed_memory, name_os_thread


class _Stoppable:
    """An executor that can stop spinning and drain before it shuts down.

    Jazzy's ``Executor.shutdown`` skips its wait for callbacks in flight (the condition is
    inverted) and destroys the wake-up guard condition under them; a callback finishing
    afterwards triggers the destroyed guard and rclpy prints an InvalidHandle traceback.
    So: stop the spin loop, let the handlers already submitted finish, then shut down.
    """

    def stop_spinning(self) -> None:
        try:
            with self._shutdown_lock:
                self._is_shutdown = True  # spin() leaves its loop; shutdown() still cleans up
                if self._guard:
                    self._guard.trigger()
        except AttributeError:  # a future rclpy without these internals: plain shutdown
            pass

    def drain(self, timeout_sec: float) -> None:
        try:
            self._work_tracker.wait(timeout_sec)
            self._executor.shutdown(wait=True)  # handlers still queued run with the guard alive
        except AttributeError:  # single-threaded: nothing runs once spin() has returned
            pass


class _DrainingExecutor(_Stoppable, SubmitOnceExecutor):
    pass


class _StoppableExecutor(_Stoppable, SingleThreadedExecutor):
    pass


def _usage(node_factory, args) -> str | None:
    """The ``--help`` text when the arguments before ``--ros-args`` ask for it, else None."""
    argv = list(sys.argv if args is None else args)
    exe = Path(argv[0]).stem if argv else "node"
    own = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if not {"-h", "--help"} & set(own):
        return None
    doc = (sys.modules[node_factory.__module__].__doc__ or "").strip()
    text = [f"usage: {exe} [--ros-args [-p NAME:=VALUE] [--params-file FILE] [-r FROM:=TO] ...]",
            "", doc]
    try:
        from ament_index_python.packages import get_package_share_directory
        config = (Path(get_package_share_directory(node_factory.__module__.split(".")[0]))
                  / "config" / f"{exe}.yaml")
        if config.is_file():
            text += ["", f"Parameters, their defaults and meaning: {config}"]
    except Exception:  # noqa: BLE001 - the help text goes without the path
        pass
    return "\n".join(text)


def run_node(node_factory, args=None, *, num_threads: int = 1) -> int:
    """Create the node, spin it until SIGINT / SIGTERM and return the exit code.

    rclpy's own handlers would shut the context down at the signal, under a frame that
    may still be publishing (a segfault in the middle layer, seen here). So we take the
    signals ourselves and tear down in order: frame worker, executor, node, context.
    A node that cannot start (bad parameters, unreadable model) logs why and returns 2;
    an error that escapes the executor (not a frame: those are contained) returns 1.
    """
    usage = _usage(node_factory, args)
    if usage is not None:  # `lmd_node --help` prints this instead of starting the node
        print(usage)
        return 0
    keep_freed_memory()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    node = executor = spinner = None
    code = 0
    try:
        node = node_factory()
        # the start-up objects (modules, models: about a million) out of the collector's
        # way, so that a full collection in a frame does not walk them all again
        gc.collect()
        gc.freeze()
        # One thread by default: the nodes' callbacks only queue frames for their worker
        # thread, and a MultiThreadedExecutor costs ~3 ms of CPU per callback here; under
        # use_sim_time (a /clock message every few ms) that was most of a core per node.
        executor = (_StoppableExecutor() if num_threads <= 1
                    else _DrainingExecutor(num_threads=num_threads))
        executor.add_node(node)
        # spin() keeps its wait set between callbacks (spin_once rebuilds it: far too
        # slow at sensor rates); it runs beside the main thread, which waits for a signal.
        crashed: list[BaseException] = []
        spinner = threading.Thread(target=_spin, args=(executor, stop, crashed), name="executor",
                                   daemon=True)
        spinner.start()
        # A node that ends by itself (the bag player) sets its ``finished`` event.
        finished = getattr(node, "finished", None)
        while not stop.wait(0.5 if finished is None else 0.05):
            if finished is not None and finished.is_set():
                break
        if crashed:
            rclpy.logging.get_logger(node.get_name()).fatal(
                f"executor stopped by an error: {type(crashed[0]).__name__}: {crashed[0]}")
            code = 1
    except Exception as exc:  # noqa: BLE001 - any start-up failure becomes exit code 2
        if node is not None:
            raise
        rclpy.logging.get_logger("lidar_quality").fatal(f"node failed to start: {exc}")
        code = 2
    finally:
        if node is not None:
            rclpy.logging.get_logger(node.get_name()).info("shutting down")
            stop_processing = getattr(node, "stop_processing", None)
            if stop_processing is not None:
                stop_processing()
        if executor is not None:
            executor.stop_spinning()
        if spinner is not None:
            spinner.join(timeout=5.0)
        if executor is not None:
            executor.drain(timeout_sec=2.0)
            executor.shutdown(timeout_sec=0)
        if node is not None:
            name = node.get_name()
            node.destroy_node()
            # a thread still in the middleware at exit can hang the process's finalization:
            # say which, so that a hang after "shutting down" has a name
            stuck = [t.name for t in threading.enumerate()
                     if t is not threading.current_thread() and t.is_alive()
                     and t.name.endswith(("_inputs", "_frames"))]
            if stuck:
                rclpy.logging.get_logger(name).error(
                    f"threads still running after teardown: {', '.join(stuck)}")
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return code


def _spin(executor, stop: threading.Event, crashed: list) -> None:
    name_os_thread("lq_executor")
    try:
        executor.spin()
    except ExternalShutdownException:
        pass
    except BaseException as exc:  # noqa: BLE001 - reported by run_node as exit code 1
        crashed.append(exc)
        raise
    finally:
        stop.set()  # spin ended (shutdown or an escaped error): let main tear down
