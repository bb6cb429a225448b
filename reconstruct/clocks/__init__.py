"""Video clocks: each video's own time mapped to one global time, recovered after the seed solve.

`estimate` fits the clocks from the solver's W links and the 2D tracks (`search`); `registered` checks clock offsets
that registration found against them.
"""
