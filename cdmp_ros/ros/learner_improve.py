"""The learner's ``~/improve`` worker and its demonstration sources (no rclpy here).

:class:`ImproveWorker` runs :class:`cdmp_ros.core.dmp.improve.Improver` in a daemon thread so the
node keeps serving its topics and services; the node polls :meth:`ImproveWorker.progress` and
:meth:`ImproveWorker.result` from its executor thread (all ROS calls stay there). The ``sim``
cost builds its pybullet world inside the worker thread and closes it there. Setting
``stop_event`` (the node's shutdown) ends the run before its next rollout cost.

:func:`resolve_bag_path` and :func:`load_bag_demonstrations` turn the ``demonstration_bags``
parameter into validated demonstrations, one entry at a time, so that a missing or corrupted
bag is reported and the others are still used.
"""
import os
import threading
import time
from typing import Callable, List, Optional, Sequence, Tuple

from cdmp_ros.core.demonstrations import Demo, map_demonstration
from cdmp_ros.core.errors import Cancelled, CdmpError, ValidationError
from cdmp_ros.core.dmp.improve import (CostConfig, ImproveConfig, ImproveResult, Improver,
                                       ScriptedCost, UpdateReport)
from cdmp_ros.core.kinematics.arms import arms_of
from cdmp_ros.core.resources import share_dirs


def resolve_bag_path(path: str) -> str:
    """An existing bag path: as given (absolute or relative to the working directory), else
    relative to the source tree or ``<prefix>/share/cdmp_ros`` (colcon/pip installs).
    Returns ``path`` unchanged when none exists (the reader then reports it)."""
    path = os.path.expanduser(path)
    if os.path.isabs(path) or os.path.exists(path):
        return os.path.abspath(path)
    for base in share_dirs():
        candidate = os.path.join(base, path)
        if os.path.exists(candidate):
            return candidate
    return path


def load_bag_demonstrations(paths: Sequence[str], topic: str, joint_names: Sequence[str],
                            lower, upper, min_samples: int, limit_tolerance: float
                            ) -> Tuple[List[Demo], List[str], List[str]]:
    """Demonstrations of every bag entry.

    Returns
    -------
    demos : list of (T, Y)
    used : list of str
        Resolved paths that gave demonstrations.
    errors : list of str
        One reason per rejected entry (missing, corrupted, wrong joints, ...).
    """
    from cdmp_ros.bag import read_demonstrations
    demos, used, errors = [], [], []
    for entry in paths:
        path = resolve_bag_path(entry)
        if not os.path.exists(path):
            errors.append(f'bag {entry!r}: not found (looked in the working directory and '
                          f'{share_dirs()})')
            continue
        try:
            raw = read_demonstrations(path, topic)
            mapped = [map_demonstration(f'bag {path} demonstration {i}', T, Y, names,
                                        joint_names, lower, upper, min_samples,
                                        limit_tolerance)
                      for i, (T, Y, names) in enumerate(raw)]
        except CdmpError as exc:
            errors.append(f'bag {entry!r}: {exc}')
            continue
        except Exception as exc:  # noqa: BLE001 -- a corrupted file may raise anything
            errors.append(f'bag {entry!r}: cannot be read ({type(exc).__name__}: {exc})')
            continue
        demos += mapped
        used.append(path)
    return demos, used, errors


class ImproveWorker(threading.Thread):
    """One ``~/improve`` run in a daemon thread.

    Parameters
    ----------
    prim : DMP or CDMP
        The primitive to improve (copied).
    config : ImproveConfig
    cost_config : CostConfig
    chain : cdmp_ros.core.kinematics.Chain
        Kinematics for the clearance term (joints in the primitive's order).
    lower, upper : ndarray
        Limits the rollouts are checked against.
    """

    def __init__(self, prim, config: ImproveConfig, cost_config: CostConfig, chain,
                 lower, upper):
        super().__init__(name='improve-worker', daemon=True)
        if getattr(prim, 'kind', None) not in ('dmp', 'cdmp'):
            raise ValidationError(f'primitive: PI2 improves dmp and cdmp primitives, got '
                                  f'{getattr(prim, "kind", type(prim).__name__)!r}')
        if chain is None:
            raise ValidationError('improve: the cost needs the robot kinematics (urdf_path) '
                                  'for the joints of the primitive')
        if len(arms_of(chain)) > 1:
            raise ValidationError('improve: the scripted cost is of one end effector; a robot '
                                  'of several arms (tip_links) has none')
        self.config = config
        self.scripted = ScriptedCost(chain, cost_config, prim.goal_y_, config.dt)
        self.cost_config = cost_config
        self.joint_names = tuple(prim.joint_names)
        self.stop_event = threading.Event()
        self.improver = Improver(prim, config, self._stoppable(self.scripted), lower, upper)
        self._lock = threading.Lock()
        self._progress: Optional[UpdateReport] = None
        self._new_progress = False
        self._result: Optional[ImproveResult] = None
        self._error: Optional[str] = None
        self.started_at = time.monotonic()
        self.elapsed = 0.0

    def run(self) -> None:
        sim = None
        try:
            if self.config.cost == 'sim':
                from cdmp_ros.sim.rollout_cost import SimRolloutCost
                sim = SimRolloutCost(self.scripted, self.cost_config.torque_weight,
                                     self.joint_names)
                self.improver.cost = self._stoppable(sim)
            result = self.improver.run(self._on_progress, self.stop_event)
            with self._lock:
                self._result = result
        except CdmpError as exc:
            with self._lock:
                self._error = str(exc)
        except Exception as exc:  # noqa: BLE001 -- report, never kill the node
            with self._lock:
                self._error = f'{type(exc).__name__}: {exc}'
        finally:
            if sim is not None:
                sim.close()
            self.elapsed = time.monotonic() - self.started_at

    def _stoppable(self, cost: Callable) -> Callable:
        """``cost`` that raises :class:`Cancelled` once ``stop_event`` is set (one rollout
        cost, not one whole update, is the longest wait of a shutdown)."""
        def stoppable_cost(traj):
            if self.stop_event.is_set():
                raise Cancelled('improvement cancelled')
            return cost(traj)
        return stoppable_cost

    def _on_progress(self, report: UpdateReport) -> None:
        with self._lock:
            self._progress = report
            self._new_progress = True

    def progress(self) -> Tuple[Optional[UpdateReport], bool]:
        """The last update report and whether it is new since the previous call."""
        with self._lock:
            new, self._new_progress = self._new_progress, False
            return self._progress, new

    def outcome(self) -> Tuple[Optional[ImproveResult], Optional[str]]:
        """(result, error) once the thread ended, else (None, None)."""
        if self.is_alive():
            return None, None
        with self._lock:
            return self._result, self._error
