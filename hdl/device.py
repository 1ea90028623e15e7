"""The device's link side in hardware: the HDL twin of :mod:`model.device` (commands and acks).

:class:`Link` receives command packets (:class:`~hdl._link_rx.LinkReceiver`), executes them
against the register map, the shadow coefficient memory and the status inputs, and answers each
with the acknowledgement bytes :class:`model.device.Device` sends, byte for byte
(:class:`~hdl._link_tx.LinkTransmitter`, which also forwards the encoded frame packets of the
frame path). Acquisition, the frame FIFO and the transmitter's line rate belong to the top level
and the UART (:mod:`hdl.uart`); Link sees only their counters.
"""

from __future__ import annotations

from functools import reduce
from operator import and_, or_

from amaranth.hdl import Cat, Const, Module, Mux, Signal
from amaranth.lib import stream, wiring
from amaranth.lib.wiring import In, Out

from model.link import (
    BANK_WORDS,
    BANK_WRITE_MAX,
    BODY_CRC,
    FIFO_BYTES,
    PROTOCOL_VERSION,
    STATUS,
    ErrorCode,
    PacketType,
)
from model.matched_filter import K_MAX, L_MAX
from model.registers import REGISTERS

from ._bram import BlockRAM
from ._crc import SplitCRC
from ._link_rx import RD_LATENCY, LinkReceiver, check_buffer_bytes, max_payload
from ._link_tx import ACK_INFO, ACK_PAYLOAD_MAX, FRAME_BYTE, LinkTransmitter
from ._primitives import OneHotFSM, _reg
from .layouts import config_signature
from .matched_filter import COEF_WRITE

# The receiver and the transmitter are private parts of Link (twin of model.device); what a
# testbench or a top level needs of them is re-exported here.
__all__ = ["ACK_LATENCY", "FRAME_BYTE", "GROUPS", "POWER_ON_COEF", "Link", "max_payload"]

#: Register groups in map order; Link has one output ``cfg_<group>`` per group.
GROUPS = tuple(dict.fromkeys(r.group for r in REGISTERS))
#: The power-on bank of ``model.device.Device``: one template of one tap, ``h[0][0]``.
POWER_ON_COEF = 1

#: Clocks from a command's last byte taken on ``rx`` to its acknowledgement's first byte on
#: ``tx`` (receiver caught up with the line, idle transmitter, ``tx`` ready), for the commands
#: answered at once. Bytes arriving on every clock add two (the receiver's sync and header
#: checks, each a clock of its own, fall behind the line). 15 until the twenty-fifth session,
#: which read the ring through the block RAM's output register (four clocks more in the
#: receiver, two in the payload's fetch), plans the answer a clock before its decision and
#: loads it a clock after.
ACK_LATENCY = 24

# payload bytes a command is checked and remembered by (BANK_COMMIT's K, L, crc is the longest)
_KEY_BYTES = 6
_FIXED_LENGTH = {
    PacketType.PING: 0, PacketType.READ_REG: 2, PacketType.WRITE_REG: 6,
    PacketType.BANK_CRC: 0, PacketType.BANK_COMMIT: 6, PacketType.START: 0,
    PacketType.STOP: 0, PacketType.STATUS: 0,
}
_COMMANDS = [c for c in PacketType if c < PacketType.ACK]
_J_BITS = (L_MAX - 1).bit_length()


class Link(wiring.Component):
    """Command side of the device: registers, coefficient bank, start/stop, status, acks.

    Parameters
    ----------
    fifo_capacity : int
        Frame FIFO capacity in bytes, reported by ``STATUS`` (the top level owns the FIFO).
    rx_buffer : int
        Receiver ring in bytes (power of two), see :class:`~hdl._link_rx.LinkReceiver`: packets
        longer than ``rx_buffer - 10`` payload bytes are rejected at the header.

    Attributes
    ----------
    rx : In(stream.Signature(8))
        Bytes from the line.
    tx : Out(stream.Signature(8))
        Bytes to the line: acknowledgements and frame packets, whole, one after the other.
    frame : In(stream.Signature(FRAME_BYTE))
        Encoded ``FRAME`` packets, ``last`` on each packet's final byte.
    cfg_stitch, cfg_gate, cfg_filter, cfg_peak : Out(config_signature(group))
        The registers, reset values at power-on; ``wiring.connect`` them to the stages' ``cfg``.
    coef : Out(stream.Signature(COEF_WRITE))
        Coefficient writes into the matched filter: ``h[0][0] = 1`` after reset (the model's
        power-on bank), then the ``K x L`` corner of the shadow at each commit.
    templates, taps : Out
        ``K`` and ``L`` of the active bank (1 and 1 at power-on).
    bank_id : Out(8)
        Commit count of the active bank.
    frame_idle : In(1)
        No frame in the filter: a commit reads it from the second clock of ``bank_busy`` on
        (the pipeline registers ``bank_busy`` before its hold, so a frame may still enter at
        the first clock's edge), and its copy starts after a clock on which it is high; so it
        must be low from the clock after an admission on.
    bank_busy : Out(1)
        Registered; from a commit's CRC match to the end of its copy: admit no new frame. The
        model switches banks the moment the command arrives; here frames already admitted
        finish with the old bank (``docs/hdl.md``, Link (HDL), commit timing).
    acquiring : Out(1)
        Between ``START`` and ``STOP``.
    frames_sent, frames_dropped, fifo_level, shots : In(32)
        Status counters of the top level, reported by ``STATUS`` as they are when it executes.

    Notes
    -----
    Latency, with the transmitter idle and ``tx`` ready: the first acknowledgement byte is on
    ``tx`` ``ACK_LATENCY = 24`` clocks after the command's last byte was taken on ``rx`` (7 to
    read the CRC byte through the receiver's ring and queue, check it and deliver, 9 to fetch
    the payload head, six bytes each ``RD_LATENCY = 3`` clocks after its offset, 3 to check it
    (``CHECK``, ``CHECK2``, ``CHECK3``), 1 to plan the answer (``PLAN``), 1 to decide, 1 to load the
    acknowledgement (``DONE``), 2 to start the packet), two more when the bytes came on
    consecutive clocks; an acknowledgement of ``n`` payload bytes then takes ``12 + n``
    clocks. ``BANK_WRITE`` of ``n`` words adds ``2 n + 3`` clocks (a payload byte per clock),
    ``BANK_CRC`` ``BANK_WORDS + 3`` (a shadow word per clock through the CRC), ``BANK_COMMIT``
    ``BANK_WORDS + 7 + 3 K L`` once ``frame_idle`` is high (the copy writes a coefficient every
    third clock: the shadow is read through the block's two registers). A command waits until
    the previous acknowledgement has left the transmitter (one buffer, which keeps the last
    acknowledgement for a retry); meanwhile the receiver's ring keeps taking bytes.
    """

    def __init__(self, fifo_capacity: int = FIFO_BYTES, rx_buffer: int = 2048):
        if not 0 < fifo_capacity < 1 << 32:
            raise ValueError(f"fifo_capacity must be in 1..2^32-1, not {fifo_capacity!r}")
        self.fifo_capacity = fifo_capacity
        self.rx_buffer = check_buffer_bytes(rx_buffer)
        super().__init__({
            "rx": In(stream.Signature(8)),
            "tx": Out(stream.Signature(8)),
            "frame": In(stream.Signature(FRAME_BYTE)),
            **{f"cfg_{g}": Out(config_signature(g)) for g in GROUPS},
            "coef": Out(stream.Signature(COEF_WRITE)),
            "templates": Out(range(K_MAX + 1), init=1),
            "taps": Out(range(L_MAX + 1), init=1),
            "bank_id": Out(8),
            "frame_idle": In(1),
            "bank_busy": Out(1),
            "acquiring": Out(1),
            "frames_sent": In(32),
            "frames_dropped": In(32),
            "fifo_level": In(32),
            "shots": In(32),
        })

    def elaborate(self, platform):
        m = Module()
        m.submodules.receiver = rx = LinkReceiver(self.rx_buffer)
        m.submodules.transmitter = tx = LinkTransmitter()
        wiring.connect(m, wiring.flipped(self.rx), rx.i)
        wiring.connect(m, tx.o, wiring.flipped(self.tx))
        wiring.connect(m, wiring.flipped(self.frame), tx.frame)

        # the shadow is read through the block's output register (two clocks), so that its
        # data drives the CRC and the coefficient port from a flip-flop (the block RAM's own
        # output, 5.8 ns from the clock, was the link's worst path once the ring's was gone)
        shadow = m.submodules.shadow = BlockRAM(16, BANK_WORDS)
        m.submodules.scan_crc = scan_crc = _bank_crc()
        m.d.comb += [shadow.r_en.eq(1), shadow.r_oce.eq(1),
                     # the CRC sees the block's output always (it takes it only while scanning):
                     # chosen by the state, the data brought the state into the CRC's network
                     scan_crc.data.eq(shadow.r_data)]

        regs = [getattr(getattr(self, f"cfg_{r.group}"), r.name) for r in REGISTERS]
        last_error = Signal(8)
        status = self._status(m, rx.bad, last_error)

        # the acknowledgement buffer: kept after sending, so a retried command is answered again
        ack = Signal(ACK_INFO)
        ack_valid = Signal()
        m.d.comb += [tx.ack.valid.eq(ack_valid), tx.ack.payload.eq(ack)]
        with m.If(tx.ack.ready):
            m.d.sync += ack_valid.eq(0)

        pkt = rx.pkt.payload
        p = [Signal(8, name=f"p{n}") for n in range(_KEY_BYTES)]  # payload head, 0 past length
        last = Signal(8 + 8 + 16 + 8 * _KEY_BYTES)  # type, seq, length, p of the last command
        last_valid = Signal()
        word = Cat(p[0], p[1])  # READ_REG/WRITE_REG address, BANK_WRITE first word
        value = Cat(p[2], p[3], p[4], p[5])  # WRITE_REG value, BANK_COMMIT crc
        k_new, l_new = p[0], p[1]
        fetch = Signal(range(_KEY_BYTES + RD_LATENCY))
        # the register address decoded from its bytes, every clock, a stage before the checks:
        # "low byte is register i's" and "high byte is zero" (every address is below 256),
        # so that the checks' decode of `word` is one AND (as a 16-bit decode, with the
        # address range test sharing its carry chain, it was the link's worst path alone on
        # seed 1, `p1` -> `chk_sel6`, 6.67 ns). The two bytes are fetched first, four clocks
        # or more before FETCH ends, so these are settled when CHECK reads them.
        assert all(r.address < 256 for r in REGISTERS)
        addr_is = [Signal(name=f"addr_is{i}") for i in range(len(REGISTERS))]
        p1_zero = Signal()
        m.d.sync += [a.eq(p[0] == r.address) for a, r in zip(addr_is, REGISTERS, strict=True)]
        m.d.sync += p1_zero.eq(p[1] == 0)
        # whether the payload has byte n, from the length (held from delivery on) a clock ahead
        has = Signal(_KEY_BYTES)
        m.d.sync += has.eq(Cat(pkt.length > n for n in range(_KEY_BYTES)))
        off = Signal(16)  # BANK_WRITE: payload byte read
        # and the bytes from it to the payload's end, `length - off`, with "more than none"
        # and "one" as flags: `off < length` and `off + 1 == length` as a compare and an add
        # of 16 bits each were the link's worst path alone on seed 1 (`off` -> `got0`, 6.54
        # ns, thirty-sixth session). Loaded from tests of the length, which is held from the
        # packet's delivery on, so they are registered every clock.
        rem = Signal(16)
        rem_some, rem_one = Signal(), Signal()
        len_m2, len_gt2, len_is3 = Signal(16), Signal(), Signal()
        m.d.sync += [len_m2.eq(pkt.length - 2), len_gt2.eq(pkt.length > 2),
                     len_is3.eq(pkt.length == 3)]
        # BANK_WRITE: whether offset `off` is in the payload, its byte the high one, the last
        got_q = [Signal(3, name=f"got{n}") for n in range(RD_LATENCY)]
        got, got_hi, got_last = got_q[-1][0], got_q[-1][1], got_q[-1][2]
        lo = Signal(8)
        waddr = Signal(range(BANK_WORDS + 1))
        scan = Signal(range(BANK_WORDS + 5))
        commit = Signal()  # the scan is a commit's check, not BANK_CRC
        crc_ok = Signal()  # the shadow's CRC is the commit's, on the clock before
        # scan = BANK_WORDS + 2, + 4, from compares a clock before: in SCAN it counts a clock
        # at a time from 0, and a scan ends by setting it to 0, so the flags are false in a
        # scan's first two clocks
        scan_at = Signal(2)
        m.d.sync += scan_at.eq(Cat(scan == BANK_WORDS + 1, scan == BANK_WORDS + 3))
        k, j = Signal(range(K_MAX)), Signal(_J_BITS)
        k_last, j_last = Signal(), Signal()  # k + 1 == K, j + 1 == L, a clock ahead
        # The shadow's read address, in no state's choice: the scan's counter and the copy's
        # (j, k) are each zero outside their own states (a scan ends by setting `scan` to 0,
        # the copy by setting j and k to 0), so their OR is the one in use. Chosen by the
        # state, the address put the executor's state three LUTs in front of the block's
        # address pins (the device's worst path on seed 2, thirty-eighth session, 8.33 ns).
        m.d.comb += shadow.r_addr.eq(scan | Cat(j, k))
        # The shadow's writes a clock after their decision, from registers: straight from
        # BANK_WRITE's flags, `got2` -> two LUTs -> the block's write enable was the whole
        # device's worst path on seed 2 (6.86 ns, 5.64 of it routing, thirty-ninth session).
        # No read can see the delay: BANK_WRITE answers after its last write, and a scan
        # starts at a later command.
        sw_en = Signal()
        sw_addr, sw_data = Signal.like(shadow.w_addr), Signal.like(shadow.w_data)
        m.d.sync += sw_en.eq(0)
        m.d.comb += [shadow.w_en.eq(sw_en), shadow.w_addr.eq(sw_addr),
                     shadow.w_data.eq(sw_data)]

        key = Cat(pkt.type, pkt.seq, pkt.length, *p)
        flags = self._checks(m, pkt, key, last, last_valid, regs, word, value, k_new, l_new,
                             addr_is, p1_zero)
        srcs = {"none": 0, "version": 1, "read": 2, "status": 3, "crc": 4, "bank": 5}
        plan = self._plan(m, flags, srcs, ack.length)

        # An answer is decided in two steps: the decision (deep: the state, the checks, the
        # command) sets a few small registers, the error code, the length and where the data
        # comes from (`src`); DONE then loads the acknowledgement's 34 bytes from them (their
        # load enable and choice, straight from the decision, were the link's worst path).
        src = Signal(range(len(srcs)))
        new_err = Signal(8)
        new_len = Signal.like(ack.length)
        # high for DONE's clock only: it loads a new acknowledgement (not a retry's, which is
        # kept as it is), it writes the register WRITE_REG addressed
        load, write = Signal(), Signal()
        m.d.sync += [load.eq(0), write.eq(0)]

        # one flip-flop per state (hdl._primitives.OneHotFSM), not a decode of a binary state
        # register (`fsm_state` -> the receiver's `base` and the plan's registers were the
        # device's worst paths, thirty-fifth session)
        fsm = OneHotFSM(m, ("BOOT", "IDLE", "FETCH", "CHECK", "CHECK2", "CHECK3", "PLAN", "DECIDE",
                            "BANK_WRITE", "SCAN", "WAIT_HOLD", "WAIT_IDLE", "COPY_READ",
                            "COPY_WAIT", "COPY_WRITE", "DONE"), name="exec")

        def answer(err, data_src, length):
            """Set the answer DONE loads (values or constants); the caller keeps a failure's
            `err` as the last error."""
            m.d.sync += [new_err.eq(err), new_len.eq(length), src.eq(data_src), load.eq(1)]
            fsm.next("DONE")

        def respond(err, data="none", nbytes=0):
            answer(Const(int(err), 8), srcs[data], 1 + nbytes)
            if int(err) != ErrorCode.OK:
                m.d.sync += last_error.eq(int(err))

        with fsm.state("BOOT"):
            m.d.comb += [self.coef.valid.eq(1), self.coef.payload.addr.eq(0),
                         self.coef.payload.data.eq(POWER_ON_COEF)]
            with m.If(self.coef.ready):
                fsm.next("IDLE")
        with fsm.state("IDLE"):
            with m.If(rx.pkt.valid & ~ack_valid):
                m.d.sync += fetch.eq(0)
                fsm.next("FETCH")
        with fsm.state("FETCH"):
            # one payload byte per clock, each RD_LATENCY clocks after its offset
            m.d.comb += rx.rd_offset.eq(fetch)
            m.d.sync += fetch.eq(fetch + 1)
            with m.Switch(fetch):
                for n in range(_KEY_BYTES):
                    with m.Case(n + RD_LATENCY):
                        m.d.sync += p[n].eq(Mux(has[n], rx.rd_data, 0))
            with m.If(fetch == _KEY_BYTES - 1 + RD_LATENCY):
                fsm.next("CHECK")
        with fsm.state("CHECK"):
            # the checks of `flags` are registered in up to three stages (CHECK, CHECK2,
            # CHECK3), so DECIDE sees them as flip-flops: compares and a choice among the
            # registers, which did not fit one clock; the plan made of them is a fourth (PLAN)
            fsm.next("CHECK2")
        with fsm.state("CHECK2"):
            fsm.next("CHECK3")
        with fsm.state("CHECK3"):
            fsm.next("PLAN")
        with fsm.state("PLAN"):
            fsm.next("DECIDE")
        with fsm.state("DECIDE"):
            m.d.sync += [last.eq(key), last_valid.eq(1),
                         ack.type.eq(PacketType.ACK | pkt.type[:7]), ack.seq.eq(pkt.seq)]
            with m.If(flags["retry"]):
                # a retry (the model's rule): the same acknowledgement, nothing redone
                # (no `load`: type and seq are the key's, as before)
                fsm.next("DONE")
            with m.Elif(plan["bank_write"]):
                m.d.sync += [off.eq(2), waddr.eq(word),
                             rem.eq(len_m2), rem_some.eq(len_gt2), rem_one.eq(len_is3)]
                m.d.sync += [g.eq(0) for g in got_q]
                fsm.next("BANK_WRITE")
            with m.Elif(plan["scan"]):
                m.d.sync += [scan.eq(0), commit.eq(plan["commit"])]
                fsm.next("SCAN")
            with m.Else():
                answer(plan["err"], plan["src"], plan["len"])
                with m.If(plan["bad"]):
                    m.d.sync += last_error.eq(plan["err"])
                m.d.sync += write.eq(plan["write"])
                with m.If(plan["start"]):
                    m.d.sync += self.acquiring.eq(1)
                with m.If(plan["stop"]):
                    m.d.sync += self.acquiring.eq(0)
        with fsm.state("BANK_WRITE"):
            # what is known of offset `off` travels beside its read, RD_LATENCY clocks
            m.d.comb += rx.rd_offset.eq(off)
            m.d.sync += [off.eq(off + 1), rem.eq(rem - 1),
                         rem_some.eq(rem_some & ~rem_one), rem_one.eq(rem == 2),
                         got_q[0].eq(Cat(rem_some, off[0], rem_one))]
            m.d.sync += [got_q[n].eq(got_q[n - 1]) for n in range(1, RD_LATENCY)]
            with m.If(got & ~got_hi):
                m.d.sync += lo.eq(rx.rd_data)
            with m.If(got & got_hi):
                m.d.sync += [sw_en.eq(1), sw_addr.eq(waddr), sw_data.eq(Cat(lo, rx.rd_data))]
                m.d.sync += waddr.eq(waddr + 1)
                with m.If(got_last):
                    respond(ErrorCode.OK)
        with fsm.state("SCAN"):
            # word a is read at scan = a and enters the CRC at scan = a + 2 from the
            # block's output register (the CRC cleared at scan = 1); the CRC is final at scan
            # = BANK_WORDS + 3 (SplitCRC's two clocks), where BANK_CRC's DONE loads it, and a
            # commit compares it there, registered, and decides a clock later
            m.d.sync += [scan.eq(scan + 1),
                         scan_crc.clear.eq(scan == 0),
                         scan_crc.valid.eq((scan >= 1) & (scan <= BANK_WORDS)),
                         crc_ok.eq(scan_crc.crc == value)]
            with m.If(scan_at[0] & ~commit):
                respond(ErrorCode.OK, "crc", 4)
                m.d.sync += scan.eq(0)  # so that no later clock sees BANK_WORDS + 3 (scan_at)
            with m.If(scan_at[1]):  # a commit's
                m.d.sync += scan.eq(0)
                with m.If(~crc_ok):
                    respond(ErrorCode.CRC_MISMATCH)
                with m.Else():
                    m.d.sync += self.bank_busy.eq(1)
                    fsm.next("WAIT_HOLD")
        with fsm.state("WAIT_HOLD"):  # the pipeline's hold takes bank_busy a clock late
            fsm.next("WAIT_IDLE")
        with fsm.state("WAIT_IDLE"):
            with m.If(self.frame_idle):
                m.d.sync += [k.eq(0), j.eq(0)]
                fsm.next("COPY_READ")
        with fsm.state("COPY_READ"):
            # the copy's end, registered here for COPY_WRITE: the adds and compares on
            # `j` and `k` were in front of the acknowledgement's registers (10.6 ns)
            m.d.sync += [j_last.eq(j + 1 == l_new), k_last.eq(k + 1 == k_new)]
            fsm.next("COPY_WAIT")
        with fsm.state("COPY_WAIT"):  # the block's second clock
            fsm.next("COPY_WRITE")
        with fsm.state("COPY_WRITE"):
            m.d.comb += [self.coef.valid.eq(1), self.coef.payload.addr.eq(Cat(j, k)),
                         self.coef.payload.data.eq(shadow.r_data)]
            with m.If(self.coef.ready):
                m.d.sync += j.eq(j + 1)
                with m.If(j_last):
                    m.d.sync += [j.eq(0), k.eq(k + 1)]
                with m.If(j_last & k_last):
                    m.d.sync += [k.eq(0),  # (zero outside the copy: the read address)
                                 self.templates.eq(k_new), self.taps.eq(l_new),
                                 self.bank_id.eq(self.bank_id + 1),
                                 self.bank_busy.eq(0)]
                    respond(ErrorCode.OK, "bank", 1)
                with m.Else():
                    fsm.next("COPY_READ")
        with fsm.state("DONE"):
            m.d.comb += rx.pkt.ready.eq(1)
            m.d.sync += ack_valid.eq(1)
            fsm.next("IDLE")
        fsm.close()

        # DONE's loads, enabled by flip-flops that are high only then (`load`, `write`), not by
        # the state's decode: from the decision, and then from the state, each was the device's
        # worst path, to the answer's 34 bytes and to registers placed beside their stages.
        # WRITE_REG's write, a clock after the decision: its enable is two flip-flops' AND.
        for on, reg in zip(flags["sel"], regs, strict=True):
            with m.If(write & on):
                m.d.sync += reg.eq(value)
        with m.If(load):
            # every source holds its value from the decision to here, the status counters but
            # for a clock, and `bank_id` is the new one already
            body = Signal(8 * (ACK_PAYLOAD_MAX - 1))
            with m.Switch(src):
                for name, data in (("version", Const(PROTOCOL_VERSION, 8)),
                                   ("read", flags["read"]), ("status", status),
                                   ("crc", scan_crc.crc), ("bank", self.bank_id)):
                    with m.Case(srcs[name]):
                        m.d.comb += body.eq(data)
            m.d.sync += [ack.length.eq(new_len), ack.data.eq(Cat(new_err, body))]
        return m

    def _status(self, m, rx_bad, last_error):
        """The ``STATUS`` record as one value, bytes little-endian in ``STATUS`` order."""
        values = {
            "frames_sent": self.frames_sent, "frames_dropped": self.frames_dropped,
            "fifo_level": self.fifo_level, "fifo_capacity": Const(self.fifo_capacity, 32),
            "rx_bad": rx_bad, "shots": self.shots, "last_error": last_error,
            "acquiring": self.acquiring, "bank_id": self.bank_id,
            "version": Const(PROTOCOL_VERSION, 8),
        }
        parts = []
        for f in STATUS.fields:
            s = Signal(f.bits, name=f"status_{f.name}")
            m.d.comb += s.eq(values[f.name])  # KeyError here: a STATUS field Link does not know
            parts.append(s)
        return Cat(*parts)

    def _checks(self, m, pkt, key, last, last_valid, regs, word, value, k_new, l_new,
                addr_is, p1_zero):
        """The tests a command's answer depends on, registered every clock (read in DECIDE).

        Most are one stage of registers from the packet; the register read, the range test
        and the retry test take two: first per register (is it the one addressed, is the value
        in its range) or per part of the key, then the choice or the AND of those flags. In
        the device the paths from the payload through a 29-way choice of registers were its
        worst (15 LUTs); the payload is held from FETCH to DECIDE, so a stage costs a clock
        of each command and nothing else. ``f["sel"]`` (one flag per register, the address
        decoded) also enables WRITE_REG's write.
        """
        f = {name: Signal(name=f"chk_{name}") for name in (
            "retry", "known", "bad_length", "bad_address", "in_range", "bw_bad_length",
            "bw_bad_address", "bad_kl")}
        f.update({c: Signal(name=f"is_{c.name.lower()}") for c in _COMMANDS})
        f["read"] = Signal(32, name="chk_read")
        # BANK_WRITE's words, from the length (held from DELIVER on, so a clock early costs
        # nothing), then the end address: each an add of its own before the compare
        n_words = Signal(15, name="chk_n_words")
        bw_end = Signal(17, name="chk_bw_end")
        m.d.sync += [n_words.eq((pkt.length - 2)[1:16]), bw_end.eq(word + n_words)]
        sel = [Signal(name=f"chk_sel{i}") for i in range(len(REGISTERS))]
        rng = [Signal(name=f"chk_rng{i}") for i in range(len(REGISTERS))]
        m.d.sync += [sel[i].eq(addr_is[i] & p1_zero) for i in range(len(REGISTERS))]
        # The range test in two stages: each 16-bit half of the value against the halves of
        # the bounds (compares with constants), then one LUT or two of those flags. As two
        # 32-bit compares, `p3` -> a chain -> `chk_rng14` was the whole device's worst path
        # on seed 1 (6.66 ns, thirty-ninth session); the stage costs a state (`CHECK3`).
        v_hi, v_lo = value[16:], value[:16]
        for i, r in enumerate(REGISTERS):
            assert 0 <= r.lo <= r.hi < 1 << 32
            halves = {"lo_gt": v_hi > r.lo >> 16, "lo_eq": v_hi == r.lo >> 16,
                      "lo_ge": v_lo >= r.lo & 0xFFFF, "hi_lt": v_hi < r.hi >> 16,
                      "hi_eq": v_hi == r.hi >> 16, "hi_le": v_lo <= r.hi & 0xFFFF}
            h = {k: _reg(m, v, 1, f"chk_{k}{i}") for k, v in halves.items()}
            m.d.sync += rng[i].eq((h["lo_gt"] | (h["lo_eq"] & h["lo_ge"]))
                                  & (h["hi_lt"] | (h["hi_eq"] & h["hi_le"])))
        m.d.sync += [
            f["read"].eq(reduce(or_, [Mux(sel[i], reg, 0) for i, reg in enumerate(regs)])),
            f["in_range"].eq(reduce(or_, [sel[i] & rng[i] for i in range(len(regs))])),
        ]
        f["sel"] = sel
        # the key compared in parts of 16 bits, then the parts' AND with the rest
        parts = [Signal(name=f"chk_same{i}") for i in range(-(-len(key) // 16))]
        m.d.sync += [parts[i].eq(last[16 * i:16 * i + 16] == key[16 * i:16 * i + 16])
                     for i in range(len(parts))]
        short = Signal(name="chk_short")
        m.d.sync += short.eq(last_valid & (pkt.length <= _KEY_BYTES))
        m.d.sync += [
            f["retry"].eq(short & reduce(and_, parts)),
            f["known"].eq(0), f["bad_length"].eq(0),
            f["bad_address"].eq(~p1_zero | (word[:8] >= len(REGISTERS))),
            f["bw_bad_length"].eq((pkt.length < 4) | pkt.length[0]
                                  | (pkt.length > 2 + 2 * BANK_WRITE_MAX)),
            f["bw_bad_address"].eq(bw_end > BANK_WORDS),
            f["bad_kl"].eq((k_new < 1) | (k_new > K_MAX) | (l_new < 1) | (l_new > L_MAX)),
        ]
        m.d.sync += [f[c].eq(pkt.type == c) for c in _COMMANDS]
        with m.Switch(pkt.type):
            for c in _COMMANDS:
                with m.Case(c):
                    m.d.sync += f["known"].eq(1)
                    if c in _FIXED_LENGTH:
                        m.d.sync += f["bad_length"].eq(pkt.length != _FIXED_LENGTH[c])
        return f

    def _plan(self, m, f, srcs, ack_length):
        """What a command that is not a retry does (the model's ``Device._execute``), worked
        out every clock from the checks and registered, so that DECIDE acts on flip-flops:
        the decision's order of tests (six deep) was the link's worst path, into the error
        register and the registers' writes.

        Returns the plan's registers: ``err`` (the answer's error code), ``bad`` (``err`` is
        not OK), ``src`` and ``len`` (the answer's data and length), and one flag per action
        besides answering: ``write`` (WRITE_REG's write), ``start``, ``stop``, ``bank_write``,
        ``scan`` (BANK_CRC and BANK_COMMIT, which answer after the scan) and ``commit``.
        """
        plan = {"err": Signal(8, name="plan_err"), "bad": Signal(name="plan_bad"),
                "src": Signal(range(len(srcs)), name="plan_src"),
                "len": Signal.like(ack_length, name="plan_len")}
        acts = ("write", "start", "stop", "bank_write", "scan", "commit")
        plan.update({a: Signal(name=f"plan_{a}") for a in acts})
        m.d.sync += [plan[a].eq(0) for a in acts]

        def answer(err, data="none", nbytes=0, act=None):
            err = int(err)
            m.d.sync += [plan["err"].eq(err), plan["bad"].eq(err != ErrorCode.OK),
                         plan["src"].eq(srcs[data]), plan["len"].eq(1 + nbytes)]
            if act is not None:
                m.d.sync += plan[act].eq(1)

        with m.If(~f["known"]):
            answer(ErrorCode.BAD_COMMAND)
        with m.Elif(f["bad_length"]):
            answer(ErrorCode.BAD_LENGTH)
        with m.Elif(f[PacketType.PING]):
            answer(ErrorCode.OK, "version", 1)
        with m.Elif(f[PacketType.READ_REG] | f[PacketType.WRITE_REG]):
            with m.If(f["bad_address"]):
                answer(ErrorCode.BAD_ADDRESS)
            with m.Elif(f[PacketType.READ_REG]):
                answer(ErrorCode.OK, "read", 4)
            with m.Elif(~f["in_range"]):
                answer(ErrorCode.BAD_VALUE)
            with m.Else():
                answer(ErrorCode.OK, act="write")
        with m.Elif(f[PacketType.BANK_WRITE]):
            with m.If(f["bw_bad_length"]):
                answer(ErrorCode.BAD_LENGTH)
            with m.Elif(f["bw_bad_address"]):
                answer(ErrorCode.BAD_ADDRESS)
            with m.Else():
                m.d.sync += plan["bank_write"].eq(1)
        with m.Elif(f[PacketType.BANK_CRC]):
            m.d.sync += plan["scan"].eq(1)
        with m.Elif(f[PacketType.BANK_COMMIT]):
            with m.If(f["bad_kl"]):
                answer(ErrorCode.BAD_VALUE)
            with m.Else():
                m.d.sync += [plan["scan"].eq(1), plan["commit"].eq(1)]
        with m.Elif(f[PacketType.START]):
            answer(ErrorCode.OK, act="start")
        with m.Elif(f[PacketType.STOP]):
            answer(ErrorCode.OK, act="stop")
        with m.Else():  # STATUS, the last command
            answer(ErrorCode.OK, "status", STATUS.size)
        return plan


def _bank_crc():
    """CRC-32 of the shadow, one s16 word per clock, its data term registered a clock before
    the state loop (:class:`hdl._crc.SplitCRC`: as the library's processor, the shadow's
    output register into the XOR trees of 16 data and 32 state bits was the link's worst path
    alone on seed 1, 6.80 ns, thirty-sixth session).

    The CRC is reflected, so a 16-bit word taken least significant bit first is its two bytes
    little-endian, the order ``BANK_CRC`` is defined over (``tests/test_hdl_link.py`` checks it
    against ``BODY_CRC.compute`` of the bytes).
    """
    return SplitCRC(BODY_CRC(16))
