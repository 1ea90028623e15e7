"""Small timing primitives shared by the gate, the frame packetizer and the pipeline's glue.

Written by hand because their point is the shape synthesis gets: a compare kept on a carry
chain, a counter step chosen among values made from the register alone, and a FIFO whose
"not empty" is a register (``amaranth.lib.fifo`` has no variant with unchecked writes and a
registered flag; its ``SyncFIFOBuffered`` level logic was a worst path of the gate).
"""

from __future__ import annotations

from amaranth.hdl import Module, Mux, Signal
from amaranth.lib import memory, stream, wiring
from amaranth.lib.wiring import In, Out

__all__ = ["_Store", "_le", "_step"]


def _le(a, b):
    """``a <= b`` as the sign of ``b - a``: one carry chain, which synthesis keeps as such
    (a compare it may turn into a tree of LUTs)."""
    return ~(b - a)[-1]


def _step(count, up, down):
    """``count + up - down`` (one-bit ``up`` and ``down``) as a choice among ``count`` and
    ``count -/+ 1``, which are made from the register alone: the late inputs then pass one
    LUT, not a carry chain."""
    return Mux(up, Mux(down, count, count + 1), Mux(down, count - 1, count))


class _Store(wiring.Component):
    """The FIFO of the gate's frame store: unchecked writes, reads as a stream.

    The writer keeps its own count of the room (the gate admits a frame only if all of it
    fits), so there is no ``w_rdy`` and a write is never refused. A write to the memory and
    the keeping of what was written are separate inputs, so that the memory's write enable
    need not wait for the writer's last decision: an entry written but not kept is
    overwritten by the next write. The oldest entry is read through the memory's synchronous
    port, whose data register is ``r.payload``. Whether the memory holds anything is a
    register (``ne``, beside the entry count), not a compare of pointers or of a level, so
    that the read decision is one LUT from registers.

    Parameters
    ----------
    width : int
        Bits per entry.
    depth : int, >= 1
        Entries it can hold, output register included; the memory is ``depth`` rounded up to a
        power of two (at least 2).

    Attributes
    ----------
    w_data : In(width)
        The entry to write.
    w_en : In(1)
        Write ``w_data`` to the memory at this clock; the writer guarantees that fewer than
        ``depth`` entries are held (kept) then.
    w_keep : In(1)
        Keep the entry written at this clock (only with ``w_en``).
    r : Out(stream.Signature(width))
        The entries, oldest first.

    Notes
    -----
    Latency: an entry written at clock t is valid on ``r`` at clock t + 2.
    """

    def __init__(self, width: int, depth: int):
        self.width, self.depth = width, depth
        super().__init__({"w_data": In(width), "w_en": In(1), "w_keep": In(1),
                          "r": Out(stream.Signature(width))})

    def elaborate(self, platform):
        m = Module()
        size = 1 << max(1, (self.depth - 1).bit_length())
        # An entry is never read on the clock it is written (the count says it is there only
        # at the next one), and the address read is never the one written then (it would take
        # `size` entries held and one more coming): the read port need not see the write
        # port, and synthesis need not build logic for a read and a write of one address
        # (`no_rw_check`).
        mem = m.submodules.mem = memory.Memory(shape=self.width, depth=size, init=[],
                                               attrs={"no_rw_check": 1})
        wp = mem.write_port()
        rp = mem.read_port()
        w_ptr = Signal(range(size))
        r_ptr = Signal(range(size))
        count = Signal(range(self.depth + 1))  # entries in the memory (output register not)
        ne = Signal()  # count != 0
        take = ne & (~self.r.valid | self.r.ready)  # oldest entry -> output register
        # The same decision again, from copies of `ne` and `r.valid` kept inverted (so that
        # synthesis does not merge them with the originals), for the count: `take` itself
        # goes to every block of the memory, and the count need not follow it there.
        empty = Signal(init=1)  # ~ne
        idle = Signal(init=1)  # ~r.valid
        take_c = ~empty & (idle | self.r.ready)
        m.d.comb += [
            wp.addr.eq(w_ptr), wp.data.eq(self.w_data), wp.en.eq(self.w_en),
            rp.addr.eq(r_ptr), rp.en.eq(take), self.r.payload.eq(rp.data),
        ]
        keep = self.w_keep
        with m.If(keep):
            m.d.sync += w_ptr.eq(w_ptr + 1)  # modulo the power-of-two size
        with m.If(take):
            m.d.sync += [r_ptr.eq(r_ptr + 1), self.r.valid.eq(1)]
        with m.Elif(self.r.ready):
            m.d.sync += self.r.valid.eq(0)
        ne_nx = keep | Mux(take_c, count != 1, ~empty)
        m.d.sync += [count.eq(_step(count, keep, take_c)), ne.eq(ne_nx), empty.eq(~ne_nx),
                     idle.eq(~take_c & (idle | self.r.ready))]
        return m
