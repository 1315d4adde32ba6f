"""The adapter's request policy without ROS (cdmp_ros.core.adaptation.session): generations,
continuing and motion-starting requests, results judged and counted, refinements."""
import types

import numpy as np
import pytest

from cdmp_ros.core.adaptation.config import (AdaptRequestConfig, AdapterConfig,
                                             AdaptationReport, ConstraintReport)
from cdmp_ros.core.adaptation.jobs import JobResult
from cdmp_ros.core.adaptation.session import (ERROR, OK, WARN, AdaptationSession,
                                              CONTINUING_TRIGGERS)
from cdmp_ros.core.kinematics import Sphere
from cdmp_ros.core.promp.promp import ProMP, RbfBasis

JOINTS = ['j1', 'j2']
LOWER, UPPER = np.array([-1.0, -1.0]), np.array([1.0, 1.0])
SPHERE = Sphere((0.1, 0.2, 0.3), 0.05)


def promp_primitive(sha1='a' * 40):
    prior = ProMP(2, RbfBasis.uniform(4), np.zeros(8), np.eye(8))
    return {'kind': 'promp', 'prim': prior, 'd': {}, 'perm': None, 'sha1': sha1,
            'limits': (LOWER * 0.5, UPPER * 0.5)}


def dmp_primitive():
    d = {'type': 'cdmp', 'joint_names': JOINTS, 'dmp': {'goal': [0.0, 0.0]}}
    return {'kind': 'cdmp', 'prim': None, 'd': d, 'perm': None, 'sha1': 'b' * 40,
            'limits': (LOWER, UPPER)}


def trigger(session, topic, now_ns=1000, stamp_ns=7, received=5.0, obstacles=(SPHERE,),
            node_config=None):
    return session.trigger(topic, stamp_ns, obstacles, np.zeros(2), AdaptRequestConfig(),
                           node_config or AdapterConfig(), now_ns, received)


def report(start='cold', kl=2.0, converged=True, constraints=()):
    return AdaptationReport(converged, 'converged' if converged else 'max_outer_reached', kl,
                            kl / 4, 3, 40, 50, 0.01, list(constraints), start=start)


def result(job, outcome='converged', start='cold', kl=2.0, stale=False, error=None,
           error_topic=None, constraints=(), infeasible=()):
    problem = types.SimpleNamespace(obstacles_used=1, obstacles_ignored=0,
                                    infeasible=list(infeasible), notes=[])
    res = None
    if outcome not in ('rejected', 'cancelled', 'kept_warm'):
        res = types.SimpleNamespace(report=report(start, kl, outcome == 'converged',
                                                  constraints), problem=problem)
    return JobResult(job, outcome, 0.02, text='{"adapted": 1}' if res else None, result=res,
                     path=np.zeros((3, 3)), band=None, error=error, error_topic=error_topic,
                     stale=stale)


def test_without_a_primitive_an_input_is_stored_and_nothing_is_solved():
    s = AdaptationSession(JOINTS)
    t = trigger(s, 'obstacles')
    assert t.action == 'wait' and t.job is None and 'obstacles stored' in t.message
    assert s.generation == 0


def test_generations_follow_the_clock_and_strictly_increase():
    s = AdaptationSession(JOINTS)
    s.set_primitive(promp_primitive())
    a = trigger(s, 'primitive', now_ns=5000).job
    b = trigger(s, 'goal', now_ns=5000).job       # the same clock reading: one more
    c = trigger(s, 'goal', now_ns=100).job        # a clock that went back (a restart)
    d = trigger(s, 'goal', now_ns=9000).job
    assert [a.generation, b.generation, c.generation, d.generation] == [5000, 5001, 5002, 9000]


def test_a_request_continues_only_after_a_motion_of_this_primitive_was_published():
    s = AdaptationSession(JOINTS)
    s.set_primitive(promp_primitive())
    start = trigger(s, 'primitive', now_ns=10).job
    assert not start.request.continues and s.restart_generation == start.generation
    # an obstacle before the motion-starting adaptation is published starts a motion too
    early = trigger(s, 'obstacles', now_ns=20).job
    assert not early.request.continues and s.restart_generation == early.generation
    # the older one's result does not end the wait: a newer motion-starting request waits
    s.result(result(start), now=6.0)
    assert s.motion_of == 0 and s.restart_generation == early.generation
    s.result(result(early), now=6.0)
    assert s.motion_of == s.primitive_id and s.restart_generation == 0
    for topic in CONTINUING_TRIGGERS:
        job = trigger(s, topic, now_ns=30).job
        assert job.request.continues and job.request.obstacles == (SPHERE,)
    goal = trigger(s, 'goal', now_ns=40).job
    assert not goal.request.continues
    # a new primitive: its motion has to start again
    s.set_primitive(promp_primitive('c' * 40))
    assert not trigger(s, 'obstacles', now_ns=50).job.request.continues


def test_the_job_carries_the_inputs_and_provenance():
    s = AdaptationSession(JOINTS)
    s.set_primitive(promp_primitive('d' * 40))
    s.set_constraints({'constraints': []})
    clipped = s.set_goal(np.array([0.9, 0.1]), None, LOWER, UPPER, margin=0.0)
    assert clipped == [0] and s.goal_y[0] <= 0.5 + 1e-12   # the primitive's limits
    job = trigger(s, 'goal', stamp_ns=123, received=4.5).job
    assert (job.trigger, job.trigger_stamp_ns, job.received) == ('goal', 123, 4.5)
    assert job.source_sha1 == 'd' * 40 and job.primitive_id == s.primitive_id
    assert job.request.constraint_doc == {'constraints': []}
    assert np.array_equal(job.request.goal_y, s.goal_y)
    assert job.request.limits == s.primitive['limits']
    assert job.request.link_balls is None                 # the links' origins
    s.link_balls = {'link1': [((0.0, 0.0, 0.1), 0.05)]}   # the node's link_geometry
    assert trigger(s, 'goal').job.request.link_balls is s.link_balls


def test_a_new_primitive_clears_the_goal_and_keeps_the_constraints():
    s = AdaptationSession(JOINTS)
    s.set_constraints({'constraints': [1]})
    s.set_goal(np.array([0.2, 0.2]), np.ones(3), LOWER, UPPER, margin=0.0)
    assert np.allclose(s.goal_y, [0.2, 0.2])      # robot limits before any primitive
    s.set_primitive(promp_primitive())
    assert s.goal_y is None and s.goal_point is None
    assert s.constraint_doc == {'constraints': [1]} and s.primitive_id == 1


def test_dmp_primitives_retarget_on_a_goal_and_only_report_otherwise():
    s = AdaptationSession(JOINTS)
    s.set_primitive(dmp_primitive())
    t = trigger(s, 'constraints')
    assert t.action == 'report' and 'applies to ProMPs' in t.message
    assert s.retarget('goal', 0, 0.0, 10) == (None, [])     # no goal yet
    assert s.counts['published'] == 0
    s.set_goal(np.array([0.3, -0.2]), None, LOWER, UPPER, margin=0.0)
    assert trigger(s, 'goal').action == 'retarget'
    left = trigger(s, 'goal', node_config=AdapterConfig(retarget_dmp_on_goal=False))
    assert left.action == 'report' and 'left to the streamer' in left.message
    assert left.retargeted['dmp']['goal'] == [0.3, -0.2]
    d, clipped = s.retarget('goal', 42, 0.0, now_ns=10**9)
    assert d['dmp']['goal'] == [0.3, -0.2] and clipped == [] and s.counts['published'] == 1
    prov = d['metadata']['adapter']
    assert prov['outcome'] == 'retargeted' and prov['source_sha1'] == 'b' * 40
    assert prov['trigger'] == 'goal' and prov['trigger_stamp_ns'] == 42
    assert prov['generation'] == 10**9 and s.generation == 10**9


def test_a_converged_result_is_published_with_its_latency_and_asks_for_a_refinement():
    s = AdaptationSession(JOINTS)
    s.set_primitive(promp_primitive())
    job = trigger(s, 'primitive', received=5.0).job
    act = s.result(result(job), now=5.25)
    assert act.publish == '{"adapted": 1}' and act.level == OK and act.refine and act.report
    assert act.values['latency_ms'] == '250.0' and act.values['outcome'] == 'converged'
    assert dict(act.timings) == {'solve': 0.02, 'request_to_publish': 0.25}
    assert s.counts['published'] == 1 and s.counts['outcome_converged'] == 1
    stale = s.result(result(trigger(s, 'goal').job, stale=True), now=6.0)
    assert stale.publish is not None and 'stale' in stale.message


def test_failed_solves_keep_the_last_primitive_and_name_what_was_violated():
    s = AdaptationSession(JOINTS)
    s.set_primitive(promp_primitive())
    bad = ConstraintReport('obstacle_0_ee', 'repeller', 0.999, 0.97, False, 20.0)
    act = s.result(result(trigger(s, 'obstacles').job, 'unconverged', constraints=[bad]),
                   now=6.0)
    assert act.publish is None and act.level == WARN and not act.refine
    assert 'obstacle_0_ee P=0.9700 < 0.999' in act.message and act.warning
    act = s.result(result(trigger(s, 'obstacles').job, 'infeasible',
                          infeasible=['obstacle 0 contains the ee at the conditioned start']),
                   now=6.0)
    assert act.level == ERROR and 'contains the ee' in act.message
    rej = s.result(result(trigger(s, 'constraints').job, 'rejected', error='bad set',
                          error_topic='constraints'), now=6.0)
    assert rej.level == ERROR and rej.reject == ('constraints', 'bad set')
    assert rej.publish is None
    assert (s.counts['outcome_unconverged'], s.counts['outcome_infeasible'],
            s.counts['outcome_rejected'], s.counts['published']) == (1, 1, 1, 0)


def test_a_result_for_a_replaced_primitive_is_dropped_without_a_report():
    s = AdaptationSession(JOINTS)
    s.set_primitive(promp_primitive())
    job = trigger(s, 'primitive').job
    s.set_primitive(promp_primitive('e' * 40))
    act = s.result(result(job), now=6.0)
    assert act.publish is None and act.level is None and not act.report
    assert s.counts['requests_outdated'] == 1 and s.counts['outcome_converged'] == 0


def test_refinements_run_only_after_a_fresh_warm_solve_with_the_solver_idle():
    s = AdaptationSession(JOINTS)
    s.set_primitive(promp_primitive())
    warm = result(trigger(s, 'obstacles', now_ns=100).job, start='warm', kl=3.0)
    assert s.refinement(warm, solver_idle=False, now_ns=200, received=7.0) is None
    assert s.refinement(result(warm.job, start='cold'), True, 200, 7.0) is None
    assert s.refinement(result(warm.job, start='warm', stale=True), True, 200, 7.0) is None
    job = s.refinement(warm, solver_idle=True, now_ns=200, received=7.0)
    assert job is not None and job.refine_kl == 3.0 and job.generation == 200
    assert job.received == 7.0 and job.refine_resume is None and job.request is warm.job.request
    assert s.counts['refinements_started'] == 1
    # a refinement of a refinement: never
    assert s.refinement(result(job, start='warm'), True, 300, 8.0) is None
    off = dict(vars(warm.job))
    off['config'] = AdaptRequestConfig(warm_start_refine=False)
    assert s.refinement(result(type(warm.job)(**off), start='warm'), True, 300, 8.0) is None


@pytest.mark.parametrize('outcome, stale, key', [('kept_warm', False, 'kept_warm'),
                                                 ('rejected', False, 'failed'),
                                                 ('rejected', True, 'cancelled'),
                                                 ('cancelled', True, 'cancelled'),
                                                 ('converged', True, 'cancelled')])
def test_a_refinement_that_publishes_nothing_is_counted_by_why(outcome, stale, key):
    s = AdaptationSession(JOINTS)
    s.set_primitive(promp_primitive())
    warm = result(trigger(s, 'obstacles').job, start='warm')
    job = s.refinement(warm, True, 10**6, 7.0)
    act = s.result(result(job, outcome, stale=stale, error='boom'), now=8.0)
    assert act.publish is None and act.level is None and act.report
    assert s.counts[f'refinements_{key}'] == 1 and s.counts['published'] == 0
    assert (act.warning is not None) == (key == 'failed')


def test_a_cancelled_refinement_resumes_on_the_next_one_and_a_cold_publication_drops_it():
    s = AdaptationSession(JOINTS)
    s.set_primitive(promp_primitive())
    first = s.refinement(result(trigger(s, 'obstacles').job, start='warm'), True, 10**6, 7.0)
    where = object()
    cancelled = result(first, 'cancelled', stale=True)
    cancelled.suspended = where
    s.result(cancelled, now=8.0)
    # the newer request's warm solve: its refinement continues the suspended one
    nxt = result(trigger(s, 'obstacles', now_ns=2 * 10**6).job, start='warm')
    assert s.result(nxt, now=8.5).refine
    again = s.refinement(nxt, True, 3 * 10**6, 9.0)
    assert again.refine_resume is where and s.counts['refinements_resumed'] == 1
    # a cold solve published: the chain restarted, nothing to resume
    s.result(result(trigger(s, 'obstacles', now_ns=4 * 10**6).job, start='cold'), now=9.5)
    later = result(trigger(s, 'obstacles', now_ns=5 * 10**6).job, start='warm')
    assert s.refinement(later, True, 6 * 10**6, 10.0).refine_resume is None


def test_a_replaced_refinement_that_never_started_counts_as_cancelled():
    s = AdaptationSession(JOINTS)
    s.set_primitive(promp_primitive())
    job = trigger(s, 'obstacles').job
    s.replaced(None)
    s.replaced(job)                       # a request replaced by a newer one: not counted here
    assert s.counts['refinements_cancelled'] == 0
    s.replaced(s.refinement(result(job, start='warm'), True, 10**6, 7.0))
    assert s.counts['refinements_cancelled'] == 1
