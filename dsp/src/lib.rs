//! Audio front end of choreod (in progress: see the audio issue).
