"""Small timing primitives shared by the gate, the frame packetizer, the peak detector and the
pipeline's glue.

Written by hand because their point is the shape synthesis gets: a compare kept on a carry
chain, a counter step chosen among values made from the register alone, a FIFO whose
"not empty" is a register (``amaranth.lib.fifo`` has no variant with unchecked writes and a
registered flag; its ``SyncFIFOBuffered`` level logic was a worst path of the gate), and a
state machine with a flip-flop per state (``m.FSM`` has no encoding choice, below).
"""

from __future__ import annotations

from contextlib import contextmanager
from functools import reduce
from operator import or_

from amaranth.hdl import Const, Module, Mux, Signal, Value, signed, unsigned
from amaranth.lib import data, memory, stream, wiring
from amaranth.lib.wiring import In, Out

from ._bram import DEEPEST, BlockRAM

__all__ = ["RAM_DELAY_MIN", "OneHotFSM", "RegisterSlice", "_Store", "_delay", "_delay_to", "_le",
           "_output_buffer", "_ram_delay", "_reg", "_room", "_step", "_sub", "_sub_sign",
           "_sum_tree", "_thermometer_next", "register_slice"]


#: Entries of the output buffer of a :class:`_Store` read free (``free_read``), counting those
#: in flight to it: the three stages from the memory and two, the fewest that sustain one
#: entry per clock with its admission (``room``) decided a clock ahead (four do not:
#: ``tests/test_hdl_bram.py``). The buffer's LUT RAM holds 8 entries for 5 as for 4.
READ_BUFFER = 5


def _le(a, b):
    """``a <= b`` as the sign of ``b - a``: one carry chain, which synthesis keeps as such
    (a compare it may turn into a tree of LUTs)."""
    return ~(b - a)[-1]


def _step(count, up, down):
    """``count + up - down`` (one-bit ``up`` and ``down``) as a choice among ``count`` and
    ``count -/+ 1``, which are made from the register alone: the late inputs then pass one
    LUT, not a carry chain."""
    return Mux(up, Mux(down, count, count + 1), Mux(down, count - 1, count))


def _fills(at_cap, below_cap, up, down):
    """``count + up - down == cap`` from the count's decoded flags ``at_cap`` (``count ==
    cap``) and ``below_cap`` (``count == cap - 1``), for a count of an admission that never
    exceeds ``cap`` (``up`` is never high at ``cap``): it reaches ``cap`` exactly when nothing
    leaves and it was at ``cap``, or one below with one in. One LUT after the flags, no carry
    chain: the admission's ``full`` register of the free-running stitch and filter."""
    return ~down & (at_cap | (below_cap & up))


def _room(count, cap, up, down):
    """``count + up - down <= cap - 1`` (one-bit ``up``, ``down``; ``count <= cap``): the
    counter's compares with constants, then one LUT with the moves."""
    return ((count <= cap - 2) | ((count == cap - 1) & (~up | down))
            | ((count == cap) & down & ~up))


def _sub(m, a, b, name):
    """``a - b`` on a signal of its own, ``{name}_sub``, signed and two bits wider than the
    wider operand (so any mix of signedness fits): one carry chain, whose sign is ``a < b``
    (:func:`_sub_sign`) and whose low bits are the difference."""
    d = Signal(signed(max(len(a), len(Value.cast(b))) + 2), name=f"{name}_sub")
    m.d.comb += d.eq(a - b)
    return d


def _sub_sign(m, a, b, name):
    """``a < b`` as the sign of ``a - b``: synthesis keeps a subtraction on the carry chain,
    where it turned the compare into a chain of six LUTs (a worst path)."""
    # The test of _le (a < b is ~_le(b, a)), but through a signal of its own (_sub): the
    # named difference is what the netlist and the timing reports show. The peak detector's
    # logic was measured with it; _le in its place would change the generated Verilog.
    return _sub(m, a, b, name)[-1]


def _reg(m, value, shape, name, reset_less=False):
    """``value`` registered: a ``Signal(shape)`` called ``name``, loaded at every clock."""
    s = Signal(shape, name=name, reset_less=reset_less)
    m.d.sync += s.eq(value)
    return s


def _cut(m, value, name):
    """``value`` on a wire that Yosys keeps (the ``keep`` attribute): ABC maps the logic on
    either side of it apart, so the wire is a LUT's output. For a choice that must stay one
    LUT of registers, where ABC would merge it with its consumers' logic and share a
    handshake's AND across them, deeper."""
    s = Signal(value.shape(), name=name, attrs={"keep": 1})
    m.d.comb += s.eq(value)
    return s


def _delay(m, value, n, name, shape=None):
    """``value`` delayed ``n`` clocks (free running); a list of all ``n + 1`` taps."""
    shape = value.shape() if shape is None else shape
    taps = [value]
    for i in range(n):
        taps.append(_reg(m, taps[-1], shape, f"{name}_{i + 1}"))
    return taps


def _ram_delay(m, value, n, name):
    """``value`` delayed ``n`` clocks (free running, ``n >= 2``) through a LUT RAM.

    For a wide value carried over many clocks: ``n`` registers per bit become a memory of
    ``n`` words (rounded up to a power of two; the ECP5's 16 x 4 LUT RAMs) and one output
    register. Each clock writes ``value`` at one pointer and reads, asynchronously, the word
    written ``n - 1`` clocks before at another (both counters, so that the read address
    comes from a register, not an adder), into the output register. The memory's words start
    at zero, as registers do, but a reset leaves them as they are, so the delayed value is
    meaningful only where the value ``n`` clocks before was written: a caller gates it with a
    valid delayed in registers.
    Returns the output register, ``name``.
    """
    shape = value.shape()
    size = max(2, 1 << (n - 1).bit_length())
    mem = memory.Memory(shape=shape, depth=size, init=[])
    m.submodules[f"{name}_mem"] = mem
    wp, rp = mem.write_port(), mem.read_port(domain="comb")
    w_ptr = Signal(range(size), name=f"{name}_wp")
    r_ptr = Signal(range(size), init=(1 - n) % size, name=f"{name}_rp")
    m.d.sync += [w_ptr.eq(w_ptr + 1), r_ptr.eq(r_ptr + 1)]
    m.d.comb += [wp.addr.eq(w_ptr), wp.data.eq(value), wp.en.eq(1), rp.addr.eq(r_ptr)]
    return _reg(m, rp.data, shape, name)


#: Clocks of delay from which :func:`_delay_to` uses a LUT RAM: below it, the RAM's pointers
#: and output register cost about what the registers would.
RAM_DELAY_MIN = 4


def _delay_to(m, value, n, name):
    """``value`` delayed ``n`` clocks (free running), the end only: registers (:func:`_delay`)
    for a short delay, a LUT RAM (:func:`_ram_delay`, its words meaningful only where the
    value ``n`` clocks before was written) from :data:`RAM_DELAY_MIN` clocks on."""
    if n >= RAM_DELAY_MIN:
        return _ram_delay(m, value, n, name)
    return _delay(m, value, n, name)[-1]


def _sum_tree(m, values, name):
    """A pipelined adder tree: one two-input level per clock; returns the root register.

    The root holds the sum of ``values`` ``ceil(log2 len(values))`` clocks after them; each
    level is one bit wider than its widest input.
    """
    level, depth = list(values), 0
    while len(level) > 1:
        depth += 1
        nxt = []
        for j in range(0, len(level), 2):
            pair = level[j:j + 2]
            shape = pair[0].shape()
            width = max(len(v) for v in pair) + 1
            total = pair[0] + pair[1] if len(pair) == 2 else pair[0]
            nxt.append(_reg(m, total, signed(width) if shape.signed else unsigned(width),
                            f"{name}_l{depth}_{j // 2}"))
        level = nxt
    return level[0]


class OneHotFSM:
    """A state machine with a flip-flop per state, written as with ``m.FSM``.

    Amaranth's ``m.FSM`` keeps a binary state register with an initial value, which Yosys's
    FSM extraction leaves as it is (it skips registers with an initial value): every state
    test is then a decode of that register and every transition a choice over all its bits
    (the packetizer's state -> decode -> next state was the pipeline's worst path, 7.4 ns).
    Here each state is a register of its own, and its next value is "here and not leaving, or
    entering": a transition (:meth:`next`, inside its state's block) is a combinational flag
    assigned under whatever conditions enclose it, so it carries them with it.

    Parameters
    ----------
    m : Module
    states : sequence of str
        The state names; the first is the initial state unless ``init`` says otherwise.
    init : str, optional
    name : str
        Prefix of the flags' names (``{name}_{state}``, lower case).

    Examples
    --------
    ::

        fsm = OneHotFSM(m, ("IDLE", "RUN"), name="ctl")
        with fsm.state("IDLE"):
            with m.If(go):
                fsm.next("RUN")
        with fsm.state("RUN"):
            fsm.next("IDLE")
        fsm.close()  # after the last block: the flags' next values
    """

    def __init__(self, m: Module, states, *, init: str | None = None, name: str = "fsm"):
        self._m = m
        self.states = tuple(states)
        if len(set(self.states)) != len(self.states) or not self.states:
            raise ValueError(f"states must be distinct names, at least one: {states!r}")
        init = self.states[0] if init is None else init
        if init not in self.states:
            raise ValueError(f"init {init!r} is not a state of {self.states!r}")
        self._flags = {s: Signal(init=int(s == init), name=f"{name}_{s.lower()}")
                       for s in self.states}
        self._name = name
        self._moves = []  # (from, to, flag)
        self._current = None
        self._closed = False

    def ongoing(self, state: str) -> Signal:
        """The flag of ``state`` (a register: high while the machine is in it)."""
        return self._flags[state]

    @contextmanager
    def state(self, state: str):
        """The block of statements active in ``state`` (``with m.If`` on its flag)."""
        if self._current is not None or self._closed:
            raise RuntimeError(f"state {state!r} opened inside {self._current!r} or after close")
        self._current = state
        try:
            with self._m.If(self._flags[state]):
                yield
        finally:
            self._current = None

    def next(self, state: str) -> None:
        """Go to ``state`` at the next clock, under the conditions enclosing this call."""
        if self._current is None:
            raise RuntimeError("next() outside a state block")
        if state not in self._flags:
            raise ValueError(f"{state!r} is not a state of {self.states!r}")
        move = Signal(name=f"{self._name}_{self._current.lower()}_to_{state.lower()}")
        self._m.d.comb += move.eq(1)
        self._moves.append((self._current, state, move))

    def close(self) -> None:
        """Drive the flags: here and not leaving, or entering."""
        self._closed = True
        for s, flag in self._flags.items():
            out = [t for a, b, t in self._moves if a == s and b != s]
            into = [t for a, b, t in self._moves if b == s and a != s]
            self._m.d.sync += flag.eq((flag & ~reduce(or_, out, Const(0)))
                                      | reduce(or_, into, Const(0)))


class _Store(wiring.Component):
    """The FIFO of the gate's frame store: unchecked writes, reads as a stream.

    The writer keeps its own count of the room (the gate admits a frame only if all of it
    fits), so there is no ``w_rdy`` and a write is never refused. A write to the memory and
    the keeping of what was written are separate inputs, so that the memory's write enable
    need not wait for the writer's last decision: an entry written but not kept is
    overwritten by the next write. The oldest entry is read through the two stages of a
    :class:`hdl._bram.BlockRAM` (the block's address register, then its output register): a
    block RAM read straight into logic is more than a 5 ns clock on the ECP5. Whether the
    memory holds anything is a register (``ne``), not a compare of pointers or of a level.

    Two ways to read. Held (the default): the block's output register is ``r.payload``, each
    stage holds its entry while the next cannot take it, and each stage's move is one LUT
    from registers and ``r.ready``. Free (``free_read``): the block reads at every clock (its
    enables are constants), its two stages and a register of the fabric after them run free,
    and an output buffer of :data:`READ_BUFFER` entries in LUT RAM
    (:func:`_output_buffer`) takes what comes out; an entry leaves the memory only while the
    buffer has room for it and those in flight, a register (``room``) counted from the
    leaves on ``r``. Then ``r.ready`` reaches no block: with the stages held, the blocks'
    enables were a LUT of it, and that LUT's route to blocks along the rows far from the
    consumer (2.3-4.3 ns in one net) was the one-lane pipeline's worst path on five seeds of
    the thirty-eighth session's runs (the packetizer's FIFO, 6.13-7.27 ns).

    Parameters
    ----------
    width : int
        Bits per entry.
    depth : int, >= 1
        Entries it can hold, those read and not yet taken from ``r`` included; the memory is
        ``depth`` rounded up to a power of two (at least 2).
    max_banks : int, optional
        For the block RAM (:class:`hdl._bram.BlockRAM`): at most this many banks of blocks,
        so at most a ``max_banks``-way mux between the blocks and their consumer.
    free_read : bool, optional
        Read as above (default False).

    Attributes
    ----------
    w_data : In(width)
        The entry to write.
    w_en : In(1)
        Write ``w_data`` to the memory at this clock; the writer guarantees that fewer than
        ``depth`` entries are held (kept) then, counting those read until they are taken
        from ``r``.
    w_keep : In(1)
        Keep the entry written at this clock (only with ``w_en``).
    r : Out(stream.Signature(width))
        The entries, oldest first.

    Notes
    -----
    Latency: an entry written at clock t is valid on ``r`` at clock t + 3 (t + 4 with
    ``free_read``); one entry per clock sustained while ``r.ready`` stays high, from a depth
    of 4 (5 with ``free_read``).
    """

    def __init__(self, width: int, depth: int, max_banks: int | None = None,
                 free_read: bool = False):
        self.width, self.depth, self.max_banks = width, depth, max_banks
        self.free_read = free_read
        super().__init__({"w_data": In(width), "w_en": In(1), "w_keep": In(1),
                          "r": Out(stream.Signature(width))})

    @staticmethod
    def memory_words(depth: int) -> int:
        """Words of the memory behind a store of ``depth`` entries: ``depth`` rounded up to
        a power of two, at least 2."""
        return 1 << max(1, (depth - 1).bit_length())

    @staticmethod
    def fewest_banks(depth: int) -> int:
        """The fewest banks of block RAM the memory of a store of ``depth`` entries can be
        tiled in (``max_banks``): one per ``DEEPEST`` words, at least one."""
        return max(1, _Store.memory_words(depth) // DEEPEST)

    def elaborate(self, platform):
        m = Module()
        size = self.memory_words(self.depth)
        # The slots in use are those of the entries in the memory and of the one in the first
        # read stage (its word is in the block's latch, which is not specified to survive a
        # rewrite of its address): at most `depth` <= `size` of them, because the writer counts
        # an entry as held until it leaves `r`. So a write never lands on the slot of an entry
        # in the first stage, and never on the slot read at that clock while the memory holds
        # an entry (that would take `size` slots in use and one more coming): the read port
        # need not see the write port. (A read of an empty memory's slot being written gives
        # the first stage a word no entry stands behind, which it does not keep.)
        ram = m.submodules.ram = BlockRAM(self.width, size, self.max_banks)
        w_ptr = Signal(range(size))
        r_ptr = Signal(range(size))
        ne = Signal()  # the memory holds an entry
        # `ne` again, inverted (so that synthesis does not merge the two), for the count and
        # the flags: `take` goes to the read pointer and the count need not follow it there.
        empty = Signal(init=1)
        keep = self.w_keep
        m.d.comb += [ram.w_addr.eq(w_ptr), ram.w_data.eq(self.w_data), ram.w_en.eq(self.w_en),
                     ram.r_addr.eq(r_ptr)]
        with m.If(keep):
            m.d.sync += w_ptr.eq(w_ptr + 1)  # modulo the power-of-two size
        read = self._read_free if self.free_read else self._read_held
        # take: the oldest entry leaves the memory; take_c: the same from `empty`; stays: an
        # entry is in the memory and none leaves
        take, take_c, stays = read(m, ram, ne, empty)
        with m.If(take):
            m.d.sync += r_ptr.eq(r_ptr + 1)
        # The entries in the memory are counted a clock late: `count1` is the last clock's
        # count, stepped by that clock's moves (registers), so that no late input (the
        # writer's keep, the port's ready) reaches the count's enables: as a step by keep and
        # take_c, r.ready -> take_c -> the enables of the packetizer FIFO's count was the
        # one-lane pipeline's worst path on seed 3 (6.31 ns, 5.1 of it routing, thirty-eighth
        # session). The moves are registered as the numbers they add, `step_k` = move - k
        # (k = 0..3), so that each use of the count is one add of two registers, one carry
        # chain: `count1` steps by `step_0`, and `below_k` (k = 1..3), "the count after this
        # clock is below k", is the sign of `count1 + step_k`. "Not empty" is decided from
        # them and this clock's move: this clock's count is >= 2 if the last was >= 1 and one
        # came in, >= 3 and one left, or >= 2 and neither, one LUT of five registers (two
        # bits of `step_0` and the three `below_k`).
        # As a choice among the count's plus and minus one and compares of it (`min(count,
        # 3)` in two bits), the count was two levels deep and its minimum three, which
        # missed 200 MHz on every seed of the forty-third session in the packetizer FIFO
        # (the count -> a carry chain -> `was_min3`, 5.57 ns); as the sign of count - 2 (a
        # chain from the count register, then two LUTs) it was the one-lane pipeline's worst
        # path on seed 2 of the thirty-seventh session, the packetizer FIFO's count -> ne,
        # 6.70 ns.
        up_nx, down_nx = keep & ~take_c, take_c & ~keep
        # (each register starts as an empty store's: no move, every `below_k` true)
        steps = [Signal(signed(4), init=-k, name=f"step_{k}") for k in range(4)]
        m.d.sync += [st.eq(Mux(up_nx, 1 - k, Mux(down_nx, -1 - k, -k)))
                     for k, st in enumerate(steps)]
        count1 = Signal(range(self.depth + 1), name="count1")
        m.d.sync += count1.eq(count1 + steps[0])
        below = [None]
        for k in (1, 2, 3):
            diff = Signal(signed(len(count1) + 2), name=f"below_{k}_sum")
            below.append(Signal(init=1, name=f"below_{k}"))
            m.d.comb += diff.eq(count1 + steps[k])
            m.d.sync += below[k].eq(diff[-1])
        down = steps[0][-1]  # the last clock's move: -1
        up = steps[0][0] & ~down  # +1
        ge2 = Mux(up, ~below[1], Mux(down, ~below[3], ~below[2]))
        ne_nx = keep | ge2 | stays
        m.d.sync += [ne.eq(ne_nx), empty.eq(~ne_nx)]
        return m

    def _read_held(self, m, ram, ne, empty):
        """The held read: the block's output register is ``r.payload``."""
        v1 = Signal()  # the first read stage holds an entry
        free_r = ~self.r.valid | self.r.ready  # `r` can take an entry at this clock
        move = v1 & free_r  # first stage -> `r`
        take = ne & (~v1 | free_r)  # oldest entry -> first stage
        # The same decisions again, from copies of the flags kept inverted (so that synthesis
        # does not merge them with the originals), for the count and the flags: `take` and
        # `move` go to every block of the memory, and the count need not follow them there.
        idle1 = Signal(init=1)  # ~v1
        idle = Signal(init=1)  # ~r.valid
        free_o = idle | self.r.ready  # = free_r
        move_c = ~idle1 & free_o
        take_c = ~empty & (idle1 | free_o)
        # The blocks' read enables ask less than `take` and `move`: the first stage reads at
        # every clock it is empty or moves on (an empty memory gives it a word it does not
        # keep), and the output register loads at every clock `r` can take a word (with none
        # in the first stage, one it does not keep): each one LUT of two flags and the ready.
        m.d.comb += [ram.r_en.eq(~v1 | free_r), ram.r_oce.eq(free_r),
                     self.r.payload.eq(ram.r_data)]
        with m.If(take):
            m.d.sync += v1.eq(1)
        with m.Elif(move):
            m.d.sync += v1.eq(0)
        with m.If(move):
            m.d.sync += self.r.valid.eq(1)
        with m.Elif(self.r.ready):
            m.d.sync += self.r.valid.eq(0)
        m.d.sync += [idle1.eq(~take_c & (idle1 | move_c)),
                     idle.eq(idle1 & free_o)]  # nothing moves to `r`, and it is free
        return take, take_c, ~empty & ~idle1 & ~free_o

    def _read_free(self, m, ram, ne, empty):
        """The free read: the block's stages and a fabric register run free into an output
        buffer; an entry leaves the memory while the buffer has room (``room``)."""
        # The entries that left the memory and have not left `r` (the buffer's admission, with
        # _output_buffer's bound: fewer than READ_BUFFER held when one comes out) are n1 -
        # left: `n1` counts the leaves a clock late (`left`, the last clock's leave), so that
        # `r.ready` reaches no enable of the count: r.ready -> the leave -> the count's enables
        # was the one-lane pipeline's worst path on seed 2 (the gate store's, 5.8 ns, most of
        # it routing, thirty-eighth session). `room` is decided a clock ahead, from the count
        # as it is (n1 - left <= READ_BUFFER - 2: with this clock's take the count is then at
        # most READ_BUFFER - 1 when `room` lets the next one go), one LUT from registers. As
        # the count after this clock's take and leave (n1 + take - left <= READ_BUFFER - 1,
        # the leave in its last LUT) it was four LUTs from `ne` through `take`: the gate
        # store's `ne` -> `room` was the one-lane pipeline's worst path on seed 2 (6.12 ns,
        # 4.63 of it routing, forty-first session). It costs the buffer one entry more.
        n1 = Signal(range(READ_BUFFER + 2))
        left = Signal()
        room = Signal(init=1)  # n1 - left <= READ_BUFFER - 2 a clock ago
        take, take_c = ne & room, ~empty & room
        m.d.comb += [ram.r_en.eq(1), ram.r_oce.eq(1)]
        # take's entry: in the block's latch a clock later, its output register two, the
        # fabric register three
        valid = _delay(m, take, 3, "read_v")
        word = _reg(m, ram.r_data, self.width, "read_word", reset_less=True)
        _output_buffer(m, self.r, READ_BUFFER, word, valid[3])
        leave = self.r.valid & self.r.ready

        # (n1 steps by `take_c`, the take made from `empty`: `ne`'s take also drives the read
        # pointer and the valid delay, and `ne` -> the take -> `n1` was the one-lane
        # pipeline's worst path on seed 1, the packetizer FIFO's, 5.63 ns, 4.6 of it routing)
        m.d.sync += [n1.eq(_step(n1, take_c, left)), left.eq(leave),
                     room.eq(Mux(left, n1 <= READ_BUFFER - 1, n1 <= READ_BUFFER - 2))]
        return take, take_c, ~empty & ~room


def _thermometer_next(t, up, down, up_top=None):
    """The next value of a count kept as a thermometer, ``t[i]`` = "more than ``i``", stepped
    by one-bit ``up`` and ``down``: a list of ``len(t)`` expressions.

    Bit ``i`` moves to its neighbour's value (``t[i - 1]`` up, ``t[i + 1]`` down, one past the
    ends) or stays: a function of three bits of the register and the two steps, one LUT where
    a binary count's step and its decoded flags were two or three (a carry chain or a decode,
    then the handshake's choice). ``up_top`` (default ``up``) is the up step of the top bit
    alone: an admission that never counts past ``len(t)`` gives the other bits its request
    without the "not full" that makes it an acceptance (below the top, a bit that moves up
    has the count below ``len(t) - 1``, where the two agree), which keeps one input fewer.
    """
    up_top = up if up_top is None else up_top
    n = len(t)
    out = []
    for i in range(n):
        below = t[i - 1] if i else Const(1)
        above = t[i + 1] if i + 1 < n else Const(0)
        u = up_top if i == n - 1 else up
        out.append(Mux(u & ~down, below, Mux(down & ~u, above, t[i])))
    return out


def _output_buffer(m: Module, o, capacity: int, pipe, pipe_valid, ahead=None,
                   valid_ahead=None, slots: int | None = None):
    """The output buffer of ``capacity`` beats behind a free-running pipeline's last stage
    ``pipe`` (the matched filter's, the stitch's): a FIFO in LUT RAM (``capacity`` rounded up
    to a power of two) whose head is also kept in a register, bypassed when empty.
    ``o.payload`` is the head register or ``pipe``.

    The caller guarantees that fewer than ``capacity`` beats are held whenever ``pipe_valid``
    is high (the pipeline's beat counts against the same admission bound).

    ``ahead`` (optional) maps fields of ``pipe`` to the values they take at the next clock
    (the stage before the last: the pipeline runs free, so that is what they become). Those
    fields of ``o.payload`` are then registers of their own, loaded with what the head-or-
    ``pipe`` mux will show at the next clock: the same values, but a consumer that decides
    on them (the detector on ``first`` and ``last``) reads a flip-flop beside it, not the
    mux's select, which fans out to the whole payload (``any_held`` -> the payload mux -> the
    detector's tag match was the pipeline's worst path, 7.61 ns, 2.6 of it the select's net).

    ``valid_ahead`` (optional) is ``pipe_valid``'s next value in the same way; ``o.valid``
    is then a register (``obuf_valid``), else the OR of ``pipe_valid`` and "any held".

    ``slots`` (optional, ``capacity`` by default, at least ``capacity - 1``): the memory's
    words before the rounding up. ``capacity - 1`` suffice: the slot of the head is dead once
    the head register holds it (the memory is read only at the slot after it), so the write
    may land there. (The default keeps the other buffers' netlists as they were measured.)
    """
    if slots is not None and not capacity - 1 <= slots:
        raise ValueError(f"slots must be at least capacity - 1 = {capacity - 1}, not {slots}")
    # The buffer was 16 register entries that moved down one at every pop, each entry's
    # select made from the `o` handshake: the pipeline's `valid` -> push/pop -> the selects of
    # 16 x 30 bits was the worst path (5.9 ns, 4.3 of it routing). Now every write is made
    # from registers only: the pipeline's beat is written at `w_ptr` whenever it is valid,
    # and the handshake only decides whether `w_ptr` moves on (whether the beat is kept; one
    # taken by the bypass is left in a free slot, to be overwritten). The slot at `w_ptr` is
    # free whenever `pipe_valid` is high, by the caller's bound. The handshake drives two
    # 4-bit pointers and the count, not the data.
    # The head is a register (`head`, a copy of the entry at `r_ptr`), refilled at a pop from
    # the entry after it, read from the RAM at `r_next` (a register, r_ptr + 1), or from the
    # pipeline's beat when that is the one that follows. Read at `r_ptr` as the payload, the
    # RAM's output went on through the pipeline's fork into the detector's decision register:
    # the pipeline's worst path (6.57 ns, 4.7 of it routing).
    size = 1 << max(1, ((capacity if slots is None else slots) - 1).bit_length())
    ram = memory.Memory(shape=pipe.shape(), depth=size, init=[])
    m.submodules.obuf = ram
    wp = ram.write_port()
    rp = ram.read_port(domain="comb")
    w_ptr = Signal(range(size), name="obuf_w_ptr")
    r_next = Signal(range(size), init=1, name="obuf_r_next")
    head = Signal.like(pipe, name="obuf_head")
    # The entries in use as a thermometer (`held[i]`: more than i; _thermometer_next): each
    # flag the head and the pointers decide on is then a register of its own. Kept as a
    # binary count with "== 1" decoded or registered beside it, every decision was a LUT of
    # the count's compares and then one of the handshake (two levels; the stitch's and the
    # stores' deepest registers, forty-ninth session).
    held = [Signal(name=f"obuf_held{i}") for i in range(capacity)]
    any_held, two_plus = held[0], held[1] if capacity > 1 else Const(0)
    # `any_held` again, inverted (so that synthesis keeps both): the select of the payload
    # mux, whose fan-out to every payload bit kept `any_held` far from the handshake's logic
    # (its first hop, 1.2 ns, began the pipeline's worst path in one seed)
    show_pipe = Signal(init=1, name="show_pipe")
    m.d.comb += [
        wp.addr.eq(w_ptr), wp.data.eq(pipe), wp.en.eq(pipe_valid),
        rp.addr.eq(r_next),
        o.payload.eq(Mux(show_pipe, pipe, head)),
    ]
    # The handshake enters as `o.ready` alone, not as the take `o.valid & o.ready`: with the
    # head held, `o.valid` is high, and with none, nothing below differs between a take and
    # none unless the pipeline's beat is there, so each use of the take is the same with the
    # ready (the head's and the count's next values are equal for both cases when `o.valid`
    # is low). `any_held` -> `o.valid` -> the take (two LUTs with the consumers' readies)
    # -> the head's select was the pipeline's worst path in two seeds (6.85-7.08 ns).
    take = o.ready
    pop = take & any_held  # the head leaves
    push = pipe_valid & ~(take & ~any_held)  # the pipeline's beat is kept
    held_nx = _thermometer_next(held, push, pop)
    # The head after this clock: at a take, the entry after it (in the RAM when two or more
    # are held, else the pipeline's beat, kept by this push, or unused); with none, the head
    # while one is held, else the pipeline's beat (kept or not: unused then). A function of
    # the take, two flags and the three values: one LUT per bit.
    head_tk = Mux(two_plus, rp.data, pipe)
    head_no = Mux(any_held, head, pipe)
    m.d.sync += [
        head.eq(Mux(take, head_tk, head_no)),
        w_ptr.eq(Mux(push, w_ptr + 1, w_ptr)),
        r_next.eq(Mux(pop, r_next + 1, r_next)),
        *(h.eq(nx) for h, nx in zip(held, held_nx, strict=True)),
        show_pipe.eq(~held_nx[0]),
    ]
    if valid_ahead is None:
        m.d.comb += o.valid.eq(any_held | pipe_valid)
    else:
        valid = Signal(name="obuf_valid")
        m.d.sync += valid.eq(held_nx[0] | valid_ahead)
        m.d.comb += o.valid.eq(valid)
    # The fields shown ahead: what the head-or-pipe mux shows next, the take choosing as for
    # the head (through the take into the pop, the head's and the count's next values and
    # then the mux, `any_held` -> the consumer's ready -> `obuf_first` was the pipeline's
    # worst path, 6.73 ns). Whether anything is held after this clock is worked out for a
    # take (a pop when anything is held) and for none, from registers, the take only
    # choosing: the handshake -> the pop -> the head's select and enable was the pipeline's
    # worst path in all three seeds of run 31 (7.3-7.7 ns).
    held_tk = (pipe_valid & any_held) | two_plus
    held_no = pipe_valid | any_held
    for name, nxt in (ahead or {}).items():
        field = getattr(o.payload, name)
        reg = Signal.like(field, name=f"obuf_{name}")
        tk, no = _shadow_queue(m, f"obuf_{name}", getattr(data.View(pipe.shape(), pipe), name),
                               held, take)
        m.d.sync += reg.eq(Mux(take, Mux(held_tk, tk, nxt), Mux(held_no, no, nxt)))
        m.d.comb += field.eq(reg)


def _shadow_queue(m: Module, name: str, beat, held, take):
    """A copy of one narrow field of the output buffer's queue in registers that move down at
    every pop (``_output_buffer``): entry i is the field of the i-th beat held (0 the head).

    Returns the head's field after this clock for a take and for none (each meaningful when
    a beat is held after it), each a LUT of registers and ``beat`` (the pipeline's field).

    The buffer keeps its beats in LUT RAM; the ahead fields (the detector's ``first`` and
    ``last``) read the entry after the head there: its read pointer -> the RAM -> the
    head-or-pipe choice -> ``obuf_last``, beside the detector, was the pipeline's worst path
    (6.01 ns, fifty-fourth session). Here the entry after the head is a flip-flop. Every
    entry's next value depends on the handshake and two thermometer flags only, as the
    buffer's own pointers do: a free entry takes the pipeline's beat (the first free one
    keeps it when it is pushed; the rest are overwritten before they are read).
    """
    n = len(held)
    q = [Signal.like(beat, name=f"{name}_q{i}") for i in range(n)]
    # at a take the queue moves down one (with nothing held, every entry is free)
    q_tk = [Mux(held[i + 1], q[i + 1], beat) if i + 1 < n else beat for i in range(n)]
    q_no = [Mux(held[i], q[i], beat) for i in range(n)]
    m.d.sync += [qi.eq(Mux(take, tk, no)) for qi, tk, no in zip(q, q_tk, q_no, strict=True)]
    return q_tk[0], q_no[0]


def _fifo_ports(width: int) -> dict:
    """The ports of an ``amaranth.lib.fifo`` FIFO (``w_rdy`` high after reset), for the FIFOs
    written here."""
    return {"w_data": In(width), "w_en": In(1), "w_rdy": Out(1, init=1),
            "r_data": Out(width), "r_en": In(1), "r_rdy": Out(1)}


class RegisterSlice(wiring.Component):
    """A stream register slice (a skid buffer): ``r_data``, ``r_rdy`` and ``w_rdy`` are each a
    flip-flop, one transfer per clock sustained, one clock of latency, two entries.

    Ports as ``amaranth.lib.fifo`` FIFOs (``w_data``, ``w_en``, ``w_rdy``, ``r_data``,
    ``r_en``, ``r_rdy``). The output register holds the oldest entry; a write that finds it
    held and not read this clock goes to the skid register, and ``w_rdy`` is low exactly while
    the skid register is full. Written by hand because ``amaranth.lib.fifo`` has no FIFO whose
    ``w_rdy`` is a register: ``SyncFIFOBuffered(depth=3)``, the slice until the thirteenth
    session, makes ``w_rdy`` a compare of its inner FIFO's level, and that compare -> the
    filter's output fork -> the side FIFO's read was the pipeline's worst path (6.67 ns, 150.0
    MHz, ``docs/fpga-history.md``). Like that slice, no path runs from ``r_en`` to ``w_rdy``.
    """

    def __init__(self, width: int):
        if not (isinstance(width, int) and width >= 1):
            raise ValueError(f"width must be an integer >= 1, not {width!r}")
        self.width = width
        super().__init__(_fifo_ports(width))

    def elaborate(self, platform):
        m = Module()
        skid = Signal(self.width)
        skid_full = ~self.w_rdy  # w_rdy is the register: low exactly while the skid is full
        write = self.w_en & self.w_rdy
        # the output register is free at this clock's edge: empty, or read now
        free = ~self.r_rdy | self.r_en
        with m.If(free):
            with m.If(skid_full):
                # the skid's entry is older than any write (none is taken while it is full)
                m.d.sync += [self.r_data.eq(skid), self.r_rdy.eq(1), self.w_rdy.eq(1)]
            with m.Else():
                m.d.sync += [self.r_data.eq(self.w_data), self.r_rdy.eq(write)]
        with m.Elif(write):
            m.d.sync += self.w_rdy.eq(0)
        # The skid register loads the input at every clock while it is empty (its value
        # matters only once it is full, and it fills at a clock when it loads the write), so
        # its clock enable is `w_rdy`, a flip-flop. As `free & write` its enable was two LUTs
        # from the neighbours' handshakes: `w_rdy` -> the gate store's read -> the enable of
        # the gate's slice, 6.9 ns, 5.4 of it routing, the one-lane pipeline's worst path on
        # seed 1 (thirty-fifth session).
        with m.If(self.w_rdy):
            m.d.sync += skid.eq(self.w_data)
        return m


def register_slice(width: int) -> RegisterSlice:
    """A stream register slice between two stages (:class:`RegisterSlice`): outputs and
    ``w_rdy`` from flip-flops, one transfer per clock. (Depth 2 of ``SyncFIFOBuffered`` would
    be a 1-entry FIFO whose ``w_rdy`` is low on the clock its entry moves out: half a transfer
    per clock; ``tests/test_hdl_pipeline.py`` checks the rate.)"""
    return RegisterSlice(width)
