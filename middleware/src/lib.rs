//! marea: a MAREA-like middleware (work in progress).
