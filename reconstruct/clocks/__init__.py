"""Video clocks: each video's own time mapped to one global time, recovered after the seed solve (docs/clocks.md).

`model` is the clock model (own time -> global time, its inverse, uncertainty and JSON form), used by every module
that maps times; `estimate` fits the clocks from the solver's W links and the 2D tracks (`search`), both started from
pair relations chained from the reference video (`chain`); `registered` checks clock offsets that registration found
against them.
"""
