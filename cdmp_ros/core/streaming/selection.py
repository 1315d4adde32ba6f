"""Which received primitive the streamer streams: the deterministic-restart rule.

The streamer receives two latched topics, ``primitive`` (from the learner) and
``adapted_primitive`` (from the adapter), in any order, for example both at once after a
restart. Every adapted primitive names, in ``metadata.adapter``, the primitive it adapts
(``source_id``: :func:`primitive_id` of the ``primitive`` message it was computed from, so the
adapter and the streamer compute the same id without the learner's help), a ``generation``
that increases with every adaptation and across adapter restarts (the adapter's ROS time in ns
at the request), and its ``trigger`` (the topic of the message that caused it) with
``trigger_stamp_ns`` (that message's header stamp, 0 if it had none). The keys are flat, so the
``trigger`` / ``trigger_stamp_ns`` the adapter wrote before keep their meaning.

:class:`AdaptationSelector` decides, without ROS:

- a ``primitive`` becomes the current one and is streamed, unless it is the current one
  again while an adaptation of it is streamed (a re-publication does not undo the adaptation);
  with ``stream_unadapted`` false it only becomes the current one, and its first adaptation is
  the first thing streamed (``primitive_awaiting_adaptation``): in a pipeline with the adapter
  the robot then executes only trajectories adapted to the constraints, never the raw prior
  (an adaptation of the previous primitive that is streaming stays until then);
- an adapted primitive of the current primitive is streamed if its generation is newer than
  the streamed adaptation's, else ignored (``adapted_ignored_old``); when it ``continues``
  the motion (obstacles, constraints) and that motion is streaming (the primitive or an
  adaptation of it), the decision says so, and the streamer keeps the current phase;
- an adapted primitive of a primitive received before the current one is dropped
  (``adapted_ignored_stale``);
- an adapted primitive of a primitive not received yet is held (the newest generation only)
  and streamed when its source arrives; a primitive other than its source drops it as stale;
- an adapted primitive without provenance (``metadata.adapter.source_id``; not from the
  adapter) is streamed as it comes, as before (``adapted_unversioned``).
"""
import hashlib
from dataclasses import dataclass, field
from typing import Any, Generic, List, Mapping, Optional, Tuple, TypeVar, Union

from cdmp_ros.core.errors import PrimitiveFileError

#: Ids of earlier primitives remembered to recognise an adaptation of an older primitive.
MAX_KNOWN_IDS = 64

Item = TypeVar('Item')


def primitive_id(text: Union[str, bytes]) -> str:
    """The id of a primitive message: SHA-1 (hex) of its JSON text (``std_msgs/String.data``),
    UTF-8 encoded. The adapter stamps it as ``metadata.adapter.source_id``."""
    if isinstance(text, str):
        text = text.encode('utf-8', 'surrogatepass')
    return hashlib.sha1(text).hexdigest()


@dataclass(frozen=True)
class Provenance:
    """What an adapted primitive says about its origin (``metadata.adapter``).

    Attributes
    ----------
    source_id : str
        :func:`primitive_id` of the adapted ``primitive`` message.
    generation : int
        Increases with every adaptation, also across adapter restarts [ns of the adapter's
        ROS clock at the request].
    trigger_topic : str
        Topic whose message caused the adaptation (``obstacles``, ``goal``, ...).
    trigger_stamp_ns : int
        Header stamp of that message [ns]; 0 when it had none (a new primitive, constraints).
    continues : bool
        The adaptation reshapes the running motion (obstacles, constraints): a streamer that
        streams its source (or an adaptation of it) continues at the current phase instead of
        restarting the motion; the adapter then did not condition phase 0 on the current
        state. False (a new primitive, a new goal): the motion restarts from the current state.
    """

    source_id: str
    generation: int
    trigger_topic: str = ''
    trigger_stamp_ns: int = 0
    continues: bool = False

    def as_dict(self) -> dict:
        """The ``metadata.adapter`` entries (``source_id``, ``generation``, ``trigger``,
        ``trigger_stamp_ns``, ``continues``)."""
        return {'source_id': self.source_id, 'generation': int(self.generation),
                'trigger': self.trigger_topic, 'trigger_stamp_ns': int(self.trigger_stamp_ns),
                'continues': bool(self.continues)}


def read_provenance(metadata: Optional[Mapping[str, Any]]) -> Optional[Provenance]:
    """The :class:`Provenance` in ``metadata.adapter``; None if it has no ``source_id``.

    Raises
    ------
    PrimitiveFileError
        When ``source_id``, ``generation``, ``trigger`` or ``trigger_stamp_ns`` are present
        but malformed.
    """
    adapter = (metadata or {}).get('adapter') if isinstance(metadata, Mapping) else None
    if not isinstance(adapter, Mapping) or 'source_id' not in adapter:
        return None
    sid, gen = adapter['source_id'], adapter.get('generation')
    if not isinstance(sid, str) or not sid:
        raise PrimitiveFileError(f'adapted_primitive.metadata.adapter.source_id: expected a '
                                 f'non-empty string, got {sid!r}')
    if isinstance(gen, bool) or not isinstance(gen, int) or gen < 0:
        raise PrimitiveFileError(f'adapted_primitive.metadata.adapter.generation: expected a '
                                 f'non-negative integer, got {gen!r}')
    topic, stamp = adapter.get('trigger', ''), adapter.get('trigger_stamp_ns', 0)
    if not isinstance(topic, str):
        raise PrimitiveFileError(f'adapted_primitive.metadata.adapter.trigger: expected a '
                                 f'topic name, got {topic!r}')
    if isinstance(stamp, bool) or not isinstance(stamp, int) or stamp < 0:
        raise PrimitiveFileError(f'adapted_primitive.metadata.adapter.trigger_stamp_ns: '
                                 f'expected a non-negative integer, got {stamp!r}')
    continues = adapter.get('continues', False)
    if not isinstance(continues, bool):
        raise PrimitiveFileError(f'adapted_primitive.metadata.adapter.continues: expected true '
                                 f'or false, got {continues!r}')
    return Provenance(sid, gen, topic, stamp, continues)


@dataclass
class Decision(Generic[Item]):
    """Outcome of an offer: the item to switch in (or None) and what was ignored.

    Attributes
    ----------
    activate : Item or None
        Switch this one in now.
    provenance : Provenance or None
        Provenance of ``activate`` when it is an adaptation.
    continues : bool
        ``activate`` reshapes the motion being streamed (its provenance ``continues``, and
        what streams now is its source or an adaptation of it): continue at the current phase.
    ignored : list of (str, str)
        ``(counter, message)`` of every item dropped or held by this offer, for diagnostics.
    """

    activate: Optional[Item] = None
    provenance: Optional[Provenance] = None
    continues: bool = False
    ignored: List[Tuple[str, str]] = field(default_factory=list)


class AdaptationSelector(Generic[Item]):
    """The deterministic-restart rule of the module docstring (no ROS, no clock).

    Items are opaque (the streamer passes prepared primitives); the selector only reads the
    ids given with them. Counters: ``adapted_ignored_stale``, ``adapted_ignored_old``,
    ``adapted_held``, ``adapted_unversioned``, ``primitive_unchanged``,
    ``primitive_awaiting_adaptation``.
    """

    def __init__(self, stream_unadapted: bool = True):
        self.stream_unadapted = stream_unadapted
        self.current_id: Optional[str] = None
        self.streamed: Optional[Provenance] = None  # the adaptation streamed now (if any)
        #: id of the primitive whose motion streams now (itself or an adaptation of it)
        self.streaming_source: Optional[str] = None
        self._held: Optional[Tuple[Provenance, Item]] = None
        self._known: List[str] = []
        self.counts = {'adapted_ignored_stale': 0, 'adapted_ignored_old': 0, 'adapted_held': 0,
                       'adapted_unversioned': 0, 'primitive_unchanged': 0,
                       'primitive_awaiting_adaptation': 0}

    @property
    def held(self) -> Optional[Provenance]:
        """Provenance of the adaptation waiting for its source, if any."""
        return self._held[0] if self._held is not None else None

    def offer_primitive(self, pid: str, item: Item) -> Decision:
        """A prepared ``primitive`` with id ``pid`` (:func:`primitive_id`)."""
        if pid == self.current_id and self.streamed is not None:
            self.counts['primitive_unchanged'] += 1
            return Decision(ignored=[('primitive_unchanged',
                                      f'primitive: unchanged (id {pid[:12]}); the adaptation '
                                      f'of generation {self.streamed.generation} stays')])
        still_streamed = self.streamed
        self.current_id, self.streamed = pid, None
        if pid in self._known:
            self._known.remove(pid)
        self._known.append(pid)
        del self._known[:-MAX_KNOWN_IDS]
        dec = Decision(activate=item)
        if self._held is not None:
            prov, held_item = self._held
            self._held = None
            if prov.source_id == pid:
                self.streamed = prov
                self.streaming_source = pid
                return Decision(activate=held_item, provenance=prov)
            dec.ignored.append(self._stale(prov))
        if self.stream_unadapted:
            self.streaming_source = pid
        else:
            # nothing is switched in: the adaptation streamed so far stays until this
            # primitive's own adaptation arrives (newer adaptations of the old one are stale)
            self.streamed = still_streamed
            self.counts['primitive_awaiting_adaptation'] += 1
            dec.activate = None
            dec.ignored.append(('primitive_awaiting_adaptation',
                                f'primitive: waiting for its adaptation (id {pid[:12]}; '
                                f'stream_unadapted is false)'))
        return dec

    def offer_adapted(self, prov: Optional[Provenance], item: Item) -> Decision:
        """A prepared ``adapted_primitive`` with its provenance (None: unversioned)."""
        if prov is None:
            self.counts['adapted_unversioned'] += 1
            self.streamed = self.streaming_source = None
            return Decision(activate=item)
        if prov.source_id == self.current_id:
            if self.streamed is not None and prov.generation <= self.streamed.generation:
                self.counts['adapted_ignored_old'] += 1
                return Decision(ignored=[(
                    'adapted_ignored_old',
                    f'adapted_primitive: generation {prov.generation} is not newer than the '
                    f'streamed {self.streamed.generation}; ignored')])
            self.streamed = prov
            continues = prov.continues and self.streaming_source == prov.source_id
            self.streaming_source = prov.source_id
            return Decision(activate=item, provenance=prov, continues=continues)
        if prov.source_id in self._known:
            return Decision(ignored=[self._stale(prov)])
        # its source has not arrived yet: hold the newest such adaptation
        if self._held is not None and self._held[0].generation >= prov.generation:
            self.counts['adapted_ignored_old'] += 1
            return Decision(ignored=[(
                'adapted_ignored_old', f'adapted_primitive: generation {prov.generation} is '
                f'older than the held {self._held[0].generation}; ignored')])
        self._held = (prov, item)
        self.counts['adapted_held'] += 1
        return Decision(ignored=[('adapted_held', f'adapted_primitive: held until its source '
                                  f'primitive (id {prov.source_id[:12]}) arrives')])

    def offer(self, topic: str, item) -> Decision:
        """Dispatch a prepared primitive by topic: ``primitive`` uses ``item.content_id``,
        any other topic (``adapted_primitive``) ``item.provenance``."""
        if topic == 'primitive':
            return self.offer_primitive(item.content_id, item)
        return self.offer_adapted(item.provenance, item)

    def values(self) -> dict:
        """Diagnostics key/values: the counters, the current primitive id and the streamed
        adaptation's generation."""
        return dict(self.counts, primitive_id=(self.current_id or 'none')[:12],
                    adapted_generation=(self.streamed.generation if self.streamed else 'none'))

    def _stale(self, prov: Provenance) -> Tuple[str, str]:
        self.counts['adapted_ignored_stale'] += 1
        return ('adapted_ignored_stale',
                f'adapted_primitive: adapts primitive {prov.source_id[:12]}, not the current '
                f'{(self.current_id or "none")[:12]}; dropped (generation {prov.generation})')
