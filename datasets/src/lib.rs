//! Motion representations and files of choreod (in progress: see the motion issue).
