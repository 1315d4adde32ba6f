"""cdmp_ros: constrained movement primitives (CDMP, constrained ProMP) for ROS 2.

The numerical core needs numpy and scipy only; its public API is importable from here::

    from cdmp_ros import CDMP, DmpConfig, ProMP, adapt, load_primitive, save_primitive

- primitives: :class:`DMP`, :class:`CDMP` (joint limits guaranteed, paper 000),
  :class:`DmpConfig`, :class:`Trajectory`; :class:`ProMP`, :class:`RbfBasis` (paper 003);
- streaming: :class:`DmpStepper` (``prim.stepper(dt)``), :class:`StepInput`,
  :class:`StepOutput`, :class:`StepStatus`; learning: :class:`Pi2`, :class:`Pi2Config`;
- constrained adaptation: :func:`adapt`, :class:`AdaptationConfig`,
  :class:`AdaptationReport`, :func:`verify`, :class:`Verification`;
- constraint sets: :func:`parse_constraint_set`, :func:`validate_constraint_set`,
  :class:`RobotContext`, and the constraints (:class:`JointLimit`, :class:`Hyperplane`,
  :class:`NonConvexCorner`, :class:`Repeller`, :class:`Waypoint`, :class:`UnboundWaypoint`,
  :class:`MutualAvoidance`, :class:`SmoothnessConstraint`) on points of interest
  (:class:`DofPoint`, :class:`ChainPoint`, :class:`DifferencePoint`);
- kinematics and obstacles: :class:`Chain`, :class:`PointOfInterest`, :func:`panda_chain`,
  :func:`planar_chain`, :func:`chain_from_urdf`, :class:`Sphere`, :class:`Box`,
  :class:`OrientedBox`; obstacle coupling: :class:`ObstacleCoupling`,
  :class:`CouplingConfig`, :class:`RepellerField`, :class:`ConstantField`,
  :class:`BoardField`;
- primitive files (``msg_schemas/primitive.schema.json``): :func:`save_primitive`,
  :func:`load_primitive`, :func:`dumps_primitive`, :func:`loads_primitive`,
  :func:`primitive_to_dict`, :func:`primitive_from_dict`;
- errors: :class:`CdmpError` and its subclasses.

Names are loaded on first use (module ``__getattr__``): ``import cdmp_ros`` imports nothing
else, so the node processes (``cdmp_ros.ros``, ``cdmp_ros.nodes``) do not pay for numpy,
scipy or the adaptation they do not use. Inside the package, modules import the defining
module, never this one.
"""
import importlib

__version__ = '0.1.0'

#: Public name -> the module that defines it.
_API = {
    **dict.fromkeys(('DMP', 'CDMP', 'DmpConfig', 'Trajectory'), 'cdmp_ros.core.dmp.dmp'),
    **dict.fromkeys(('ProMP', 'RbfBasis'), 'cdmp_ros.core.promp.promp'),
    **dict.fromkeys(('DmpStepper', 'StepInput', 'StepOutput', 'StepStatus'),
                    'cdmp_ros.core.dmp.stepper'),
    **dict.fromkeys(('Pi2', 'Pi2Config'), 'cdmp_ros.core.dmp.pi2'),
    'adapt': 'cdmp_ros.core.adaptation.guarantee',
    **dict.fromkeys(('AdaptationConfig', 'AdaptationReport'), 'cdmp_ros.core.adaptation.config'),
    'verify': 'cdmp_ros.core.adaptation.verification',
    'Verification': 'cdmp_ros.core.adaptation.verification_report',
    **dict.fromkeys(('parse_constraint_set', 'validate_constraint_set', 'RobotContext'),
                    'cdmp_ros.core.adaptation.constraints.parse'),
    'JointLimit': 'cdmp_ros.core.adaptation.constraints.limits',
    **dict.fromkeys(('Hyperplane', 'NonConvexCorner'),
                    'cdmp_ros.core.adaptation.constraints.hyperplane'),
    **dict.fromkeys(('Repeller', 'Waypoint', 'UnboundWaypoint', 'MutualAvoidance'),
                    'cdmp_ros.core.adaptation.constraints.spheres'),
    'SmoothnessConstraint': 'cdmp_ros.core.adaptation.constraints.smoothness',
    **dict.fromkeys(('DofPoint', 'ChainPoint', 'DifferencePoint'),
                    'cdmp_ros.core.adaptation.constraints.points'),
    **dict.fromkeys(('Chain', 'PointOfInterest'), 'cdmp_ros.core.kinematics.chain'),
    **dict.fromkeys(('panda_chain', 'planar_chain', 'chain_from_urdf'),
                    'cdmp_ros.core.kinematics.builders'),
    **dict.fromkeys(('Sphere', 'Box', 'OrientedBox'), 'cdmp_ros.core.kinematics.closest'),
    **dict.fromkeys(('ObstacleCoupling', 'CouplingConfig'), 'cdmp_ros.core.coupling.obstacle'),
    **dict.fromkeys(('RepellerField', 'ConstantField', 'BoardField'),
                    'cdmp_ros.core.coupling.potential_fields'),
    **dict.fromkeys(('save_primitive', 'load_primitive', 'dumps_primitive', 'loads_primitive',
                     'primitive_to_dict', 'primitive_from_dict'), 'cdmp_ros.core.primitive_io'),
    **dict.fromkeys(('CdmpError', 'ValidationError', 'PrimitiveFileError', 'ConstraintSetError',
                     'Cancelled'), 'cdmp_ros.core.errors'),
}

__all__ = sorted(_API) + ['__version__']


def __getattr__(name: str):
    """Import the public ``name`` from its module on first use (then cached here)."""
    module = _API.get(name)
    if module is None:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
