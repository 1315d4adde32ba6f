"""AdaptationSelector: the deterministic-restart rule of the streamer, in every arrival order."""
import itertools

import pytest

from cdmp_ros.core.errors import PrimitiveFileError
from cdmp_ros.core.primitive_io import dumps_primitive
from cdmp_ros.core.streaming.primitives import prepare_primitive
from cdmp_ros.core.streaming.selection import (AdaptationSelector, Provenance, primitive_id,
                                               read_provenance)
from streamer_harness import LOWER, PANDA_JOINTS, UPPER, reach_cdmp

P1, P2, P3 = primitive_id('{"p": 1}'), primitive_id('{"p": 2}'), primitive_id('{"p": 3}')


def adapted(source, gen, stamp=0):
    return Provenance(source, gen, 'obstacles', stamp)


def run(events, stream_unadapted=True):
    """Feed events ('p', id) / ('a', Provenance); returns the selector and what was streamed
    (in order, as labels)."""
    sel = AdaptationSelector(stream_unadapted)
    streamed = []
    for kind, x in events:
        if kind == 'p':
            dec = sel.offer_primitive(x, f'P:{x[:4]}')
        else:
            dec = sel.offer_adapted(x, 'A:none' if x is None
                                    else f'A:{x.source_id[:4]}:{x.generation}')
        if dec.activate is not None:
            streamed.append(dec.activate)
    return sel, streamed


def test_primitive_id_is_the_sha1_of_the_utf8_text():
    assert primitive_id('{"a": "é"}') == primitive_id('{"a": "é"}'.encode('utf-8'))
    assert primitive_id('x') == '11f6ad8ec52a2984abaafd7c3b516503785c2072'
    assert primitive_id('x') != primitive_id('x ')


def test_primitive_then_its_adaptation_streams_both_in_turn():
    sel, streamed = run([('p', P1), ('a', adapted(P1, 10))])
    assert streamed == [f'P:{P1[:4]}', f'A:{P1[:4]}:10']
    assert sel.streamed.generation == 10


def test_adaptation_then_its_primitive_streams_the_adaptation():
    sel, streamed = run([('a', adapted(P1, 10)), ('p', P1)])
    assert streamed == [f'A:{P1[:4]}:10']
    assert sel.counts['adapted_held'] == 1 and sel.held is None


@pytest.mark.parametrize('order', ['primitive first', 'adaptation first'])
def test_without_stream_unadapted_only_adaptations_are_streamed(order):
    """stream_unadapted false: a primitive is only recorded as the source; its adaptation, in
    either arrival order, is the first thing streamed; a newer primitive waits again, and an
    adaptation of the older one stays stale."""
    events = [('p', P1), ('a', adapted(P1, 10))]
    if order == 'adaptation first':
        events.reverse()
    sel, streamed = run(events + [('p', P2), ('a', adapted(P1, 11)), ('a', adapted(P2, 12))],
                        stream_unadapted=False)
    assert streamed == [f'A:{P1[:4]}:10', f'A:{P2[:4]}:12']
    assert sel.counts['primitive_awaiting_adaptation'] == (2 if order == 'primitive first'
                                                           else 1)
    assert sel.counts['adapted_ignored_stale'] == 1
    assert sel.streamed.generation == 12
    dec = AdaptationSelector(False).offer_primitive(P3, 'P3')
    assert dec.activate is None and dec.ignored[0][0] == 'primitive_awaiting_adaptation'
    # a new primitive while an adaptation streams: that adaptation stays (and is reported)
    sel, streamed = run([('p', P1), ('a', adapted(P1, 10)), ('p', P2)], stream_unadapted=False)
    assert streamed == [f'A:{P1[:4]}:10'] and sel.current_id == P2
    assert sel.streamed.generation == 10


def test_adaptation_of_an_older_primitive_is_never_streamed():
    # live: P1, then P2; an adaptation of P1 (solved before P2 arrived) comes late
    sel, streamed = run([('p', P1), ('p', P2), ('a', adapted(P1, 10))])
    assert streamed == [f'P:{P1[:4]}', f'P:{P2[:4]}']
    assert sel.counts['adapted_ignored_stale'] == 1
    # restart: the latched adaptation of P1 arrives before the latched P2
    sel, streamed = run([('a', adapted(P1, 10)), ('p', P2)])
    assert streamed == [f'P:{P2[:4]}']
    assert sel.counts['adapted_ignored_stale'] == 1 and sel.held is None


def test_out_of_order_generations_keep_the_newest():
    sel, streamed = run([('p', P1), ('a', adapted(P1, 20)), ('a', adapted(P1, 10)),
                         ('a', adapted(P1, 20)), ('a', adapted(P1, 30))])
    assert streamed == [f'P:{P1[:4]}', f'A:{P1[:4]}:20', f'A:{P1[:4]}:30']
    assert sel.counts['adapted_ignored_old'] == 2
    # held before the source: the newest held one wins, an older one is ignored
    sel, streamed = run([('a', adapted(P1, 20)), ('a', adapted(P1, 10)), ('p', P1)])
    assert streamed == [f'A:{P1[:4]}:20']
    sel, streamed = run([('a', adapted(P1, 10)), ('a', adapted(P1, 20)), ('p', P1)])
    assert streamed == [f'A:{P1[:4]}:20']


def test_republished_primitive_keeps_the_adaptation_and_a_new_one_resets_it():
    sel, streamed = run([('p', P1), ('a', adapted(P1, 10)), ('p', P1)])
    assert streamed[-1] == f'A:{P1[:4]}:10' and sel.counts['primitive_unchanged'] == 1
    # a new primitive replaces the adaptation; a later adaptation of it with a smaller
    # generation than the old one's is still streamed (generations compare per source)
    sel, streamed = run([('p', P1), ('a', adapted(P1, 10)), ('p', P2), ('a', adapted(P2, 5))])
    assert streamed[-2:] == [f'P:{P2[:4]}', f'A:{P2[:4]}:5']
    # going back to an earlier primitive: its adaptations are current again
    sel, streamed = run([('p', P1), ('p', P2), ('p', P1), ('a', adapted(P1, 7))])
    assert streamed[-1] == f'A:{P1[:4]}:7' and sel.counts['adapted_ignored_stale'] == 0


def test_unversioned_adaptation_is_streamed_as_before():
    sel, streamed = run([('p', P1), ('a', None)])
    assert len(streamed) == 2 and sel.streamed is None
    assert sel.counts['adapted_unversioned'] == 1


@pytest.mark.parametrize('order', list(itertools.permutations(range(4))))
def test_restart_in_any_order_streams_the_newest_adaptation_of_the_current_primitive(order):
    """Whatever the order of {P3, A(P1), A(P3) g1, A(P3) g2} with P1 and P2 seen before, the
    last thing streamed is A(P3) g2 and no adaptation of P1 is ever streamed."""
    ev = [('p', P3), ('a', adapted(P1, 50)), ('a', adapted(P3, 60)), ('a', adapted(P3, 70))]
    sel, streamed = run([('p', P1), ('p', P2)] + [ev[i] for i in order])
    assert streamed[-1] == f'A:{P3[:4]}:70'
    assert not any(s.startswith(f'A:{P1[:4]}') for s in streamed)


def test_read_provenance_accepts_the_adapter_metadata_and_names_bad_fields():
    prov = adapted(P1, 123, 456)
    assert read_provenance({'adapter': prov.as_dict()}) == prov
    assert read_provenance({}) is None and read_provenance(None) is None
    assert read_provenance({'adapter': {'outcome': 'retargeted'}}) is None
    for bad, field in [({'source_id': 3, 'generation': 1}, 'source_id'),
                       ({'source_id': P1, 'generation': -1}, 'generation'),
                       ({'source_id': P1, 'generation': True}, 'generation'),
                       ({'source_id': P1, 'generation': 1, 'trigger': 5}, 'trigger'),
                       ({'source_id': P1, 'generation': 1, 'trigger_stamp_ns': 1.5},
                        'trigger_stamp_ns'),
                       ({'source_id': P1, 'generation': 1, 'continues': 'yes'}, 'continues')]:
        with pytest.raises(PrimitiveFileError, match=field):
            read_provenance({'adapter': bad})


def test_a_continuing_adaptation_continues_only_the_motion_that_streams():
    cont = Provenance(P1, 5, 'obstacles', 0, continues=True)
    assert read_provenance({'adapter': cont.as_dict()}) == cont
    # the primitive streams, then adaptations of it: they continue it (if they say so)
    sel = AdaptationSelector()
    sel.offer_primitive(P1, 'p1')
    assert sel.offer_adapted(cont, 'a5').continues
    assert not sel.offer_adapted(Provenance(P1, 6, 'goal', 0), 'a6').continues
    assert sel.offer_adapted(Provenance(P1, 7, 'obstacles', 0, True), 'a7').continues
    # without stream_unadapted the first adaptation starts the motion: nothing to continue
    sel = AdaptationSelector(stream_unadapted=False)
    sel.offer_primitive(P1, 'p1')
    dec = sel.offer_adapted(cont, 'a5')
    assert dec.activate == 'a5' and not dec.continues
    assert sel.offer_adapted(Provenance(P1, 6, 'obstacles', 0, True), 'a6').continues
    # a new primitive awaits its adaptation while P1's motion streams on: P2's first
    # adaptation starts P2's motion
    sel.offer_primitive(P2, 'p2')
    dec = sel.offer_adapted(Provenance(P2, 7, 'obstacles', 0, True), 'b7')
    assert dec.activate == 'b7' and not dec.continues
    # an adaptation held until its source arrives starts that motion
    sel = AdaptationSelector()
    assert sel.offer_adapted(cont, 'a5').activate is None
    dec = sel.offer_primitive(P1, 'p1')
    assert dec.activate == 'a5' and not dec.continues


def test_prepare_primitive_keeps_the_content_id_and_metadata():
    prim = reach_cdmp()
    prim.metadata = {'adapter': adapted(P1, 9).as_dict()}
    text = dumps_primitive(prim)
    prep = prepare_primitive(text, PANDA_JOINTS, 0.002, LOWER, UPPER)
    assert prep.content_id == primitive_id(text)
    assert read_provenance(prep.metadata) == adapted(P1, 9)
