//! FPMa: the USAL Flight Plan Manager (work in progress).
