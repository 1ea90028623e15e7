"""Testbench tooling for the HDL: traffic patterns and payload packing (``streams``), the
generic cocotb bench (``cocotb_bench``), the Verilator runner with its build cache (``cosim``)
and the same traffic in Amaranth's simulator (``amsim``). Not hardware: nothing here is a stage,
so nothing here has a model twin."""
