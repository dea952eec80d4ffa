"""The reference's search over event sequences, split by concern.

:func:`~hybridoc.reference.solve_reference` (:mod:`hybridoc.reference.solve`) solves one
problem by solving event sequences and keeping the best verified extremal. Which sequences
it solves, what it remembers of them and what it may claim from them is the search, in
four modules:

:mod:`~hybridoc.reference.search.book`
    The bookkeeping: what one call tried and knows (``Book``), its checked arguments
    (``Run``), the initial guess as the search uses it (``Guess``), the controls met
    (``Known``) and whether they are feasible (``is_feasible``, ``path_violation``), and
    the limits the search is held to.
:mod:`~hybridoc.reference.search.discovery`
    The discovery of sequences: the initial guess's candidates, the candidate sources'
    proposals, the enumeration and the sequences of re-simulations (``discover``); the
    known controls that are cheaper (``revisit_cheaper``); the second starts of Newton
    that the proof needs (``second_start``); a given sequence's extremal
    (``solve_given``).
:mod:`~hybridoc.reference.search.enumeration`
    The enumeration: every feasible sequence, length by length and by lower bound within
    a length (``run_enumeration``), each screened by Newton in worker processes where the
    platform can fork (``start_screens``).
:mod:`~hybridoc.reference.search.claims`
    What the search claims: the proof of the global optimum from its coverage
    (``proof``), the checks of an answer, and the Solution with its coverage
    (``finish``, ``coverage_line``, ``families_line``).

The modules are imported by their own names; the package re-exports nothing.
"""
