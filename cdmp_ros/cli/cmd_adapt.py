"""``cdmp adapt``: adapt a ProMP primitive file to a constraint set (paper 003) and print the
optimiser's report.

    cdmp adapt --primitive p.json --constraints c.json --robot planar4|panda|dual_panda|none \
        --out adapted.json

The optimiser stops at a KKT point (``--stop-rule kkt``, the default here: each constraint
whose multiplier matters sits at about ``violation_target`` of its allowed violation, the KL is
minimal, relaxing alpha buys freedom) or, with ``--stop-rule feasible``, at the first iterate
where every constraint holds (the paper's rule; the adapter node's, for latency).

The report (text, or JSON with ``--json``; also in the adapted file's metadata) gives the
optimiser's figures, its KKT residuals (``kkt``) and a sampled verification of the adapted
distribution: per constraint the sampled per-step maximum violation and the trajectory-level
violation (fraction of sampled trajectories violating it at any step) with its 95 % upper
confidence bound (one-sided Clopper-Pearson), and the overall trajectory-level violation
(any constraint); JSON key ``verification``: {"n_samples", "trajectory_violation",
"trajectory_violation_upper95", "constraints": [{"name", "per_step_max", "trajectory",
"upper95", ...}]}. Each constraint's optimiser figures (JSON ``constraints``) name the law of
its probability (``law``: ``gaussian`` for linear forms, the tail of the quadratic forms, or
``gamma, importance-sampled check`` for link points under the default tail and check), and
``n_level_corrections`` counts the re-solves that check tightened.

Exit status: 0 when every constraint holds at its confidence (converged: under the
optimiser's approximation and by the sampled verification, per step or per trajectory as the
set's ``guarantee`` says), 2 when the problem is infeasible or unconverged or the verification
does not confirm the claimed level (the adapted primitive is still written, with the report in
its metadata), 1 on malformed input.
"""
import json
import sys

NAME = 'adapt'
HELP = 'adapt a ProMP primitive file to a constraint set and print the verified report'
DESCRIPTION = ('Adapt a ProMP primitive file to a constraint set (paper 003) and print the '
               'report with its sampled verification (per constraint: per-step maximum '
               'violation, trajectory-level violation and its 95 % upper bound). The set '
               'field "guarantee" ("per_step", default, or "trajectory") says what alpha '
               'claims. Exit status: 0 converged and verified, 2 infeasible, unconverged or '
               'not verified (the adapted file is still written), 1 malformed input.')
ROBOTS = ('none', 'planar4', 'panda', 'dual_panda')
STOP_RULES = ('feasible', 'kkt')   # cdmp_ros.core.adaptation.config.STOP_RULES (cheap import)


def add_arguments(parser):
    parser.add_argument('--primitive', required=True, help='ProMP primitive file (*.json)')
    parser.add_argument('--constraints', required=True, help='constraint set file (*.json)')
    parser.add_argument('--robot', choices=ROBOTS, default='none',
                        help='kinematics of link points of interest (none: the ProMP '
                             'dimensions are the coordinates)')
    parser.add_argument('--out', required=True, help='adapted primitive file to write')
    parser.add_argument('--json', action='store_true',
                        help='print the report as JSON (sampled figures under "verification")')
    parser.add_argument('--seed', type=int, default=0,
                        help='seed of the sampled verification (default 0: reproducible)')
    parser.add_argument('--stop-rule', choices=STOP_RULES, default=None,
                        help="when the optimiser stops: kkt (default, unless the set's "
                             'optimizer.stop_rule says otherwise) at a KKT point, every '
                             'binding constraint at its level and the KL minimal; feasible '
                             "at the first iterate where every constraint holds (the paper's "
                             'rule, faster, further from the prior than needed)')


def robot_context(robot: str, n_dims: int):
    """RobotContext for a named robot (planar4: 4 links of 1 m in the xy plane)."""
    from cdmp_ros.core.adaptation.constraints.parse import RobotContext
    from cdmp_ros.core.errors import ValidationError
    from cdmp_ros.core.kinematics import dual_panda_chains, panda_chain, planar_chain
    need = {'planar4': 4, 'panda': 7, 'dual_panda': 14}.get(robot)
    if need is not None and n_dims != need:
        raise ValidationError(f'--robot {robot}: expected a primitive with {need} dimensions, '
                              f'got {n_dims}')
    if robot == 'none':
        return RobotContext(n_dims)
    if robot == 'planar4':
        return RobotContext(n_dims, [(planar_chain([1.0] * 4), range(4))], axes=(0, 1))
    from cdmp_ros.sim.robot_specs import panda_urdf_path
    if robot == 'panda':
        return RobotContext(n_dims, [(panda_chain(panda_urdf_path()), range(7))])
    left, right = dual_panda_chains(panda_urdf_path())
    return RobotContext(n_dims, [(left, range(7)), (right, range(7, 14))])


def run(args):
    from cdmp_ros.core.adaptation.guarantee import adapt
    from cdmp_ros.core.adaptation.solver import AdaptationConfig
    from cdmp_ros.core.adaptation.constraints.parse import parse_constraint_set
    from cdmp_ros.core.errors import CdmpError
    from cdmp_ros.core.primitive_io import load_primitive, save_primitive
    try:
        prim = load_primitive(args.primitive)
        if getattr(prim, 'kind', None) != 'promp':
            print(f'cdmp adapt: --primitive: expected kind "promp", got '
                  f'{getattr(prim, "kind", "?")!r}', file=sys.stderr)
            return 1
        try:
            with open(args.constraints) as f:
                doc = json.load(f)
        except (OSError, json.JSONDecodeError) as exc:
            print(f'cdmp adapt: --constraints: {exc}', file=sys.stderr)
            return 1
        ctx = robot_context(args.robot, prim.n_dims)
        constraints, overrides = parse_constraint_set(doc, prim, ctx)
        overrides.setdefault('stop_rule', 'kkt')
        if getattr(args, 'stop_rule', None):
            overrides['stop_rule'] = args.stop_rule
        config = AdaptationConfig(**overrides)
    except CdmpError as exc:
        print(f'cdmp adapt: {exc}', file=sys.stderr)
        return 1
    import numpy as np
    adapted, report = adapt(prim, constraints, config,
                            rng=np.random.default_rng(getattr(args, 'seed', 0)))
    adapted.metadata = dict(getattr(prim, 'metadata', {}) or {})
    adapted.metadata['adaptation'] = report.as_dict()
    save_primitive(adapted, args.out)
    print(json.dumps(report.as_dict(), indent=2) if args.json else report.to_text())
    return 0 if report.converged else 2
