//! Loss from MAVLink sequence numbers: the one rule the node (its vehicle link), the ground
//! station (every source on every link) and the MAVProxy module (through the Python package)
//! count frames lost by. One tracker per sender (system, component) and link; the number wraps
//! at 256.
//!
//! With `skipped = seq - last - 1` (mod 256), for each frame after the first:
//! - `seq == last`: a **repeat** (the same frame twice); nothing lost, nothing followed;
//! - `skipped` in 0..128: `skipped` frames were **lost**; the tracker follows `seq`;
//! - `seq` behind `last` by 1..=[`MAX_REORDER`]: a **late** frame, overtaken on the way: it was
//!   counted lost in its gap, so one loss is taken back (never below zero); not followed;
//! - further behind: the sender **restarted** (its numbers began again); followed, nothing lost.
//!
//! A restart that lands within [`MAX_REORDER`] behind the last number reads as up to that many
//! late frames; a burst of 128 or more losses reads as a restart. Neither is separable from the
//! number alone.

/// How far behind the last number a frame is taken for a late one, not a restarted sender.
pub const MAX_REORDER: u8 = 16;

/// Frames received, lost, late and repeated from one sender on one link.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SequenceTracker {
    last: Option<u8>,
    pub received: u64,
    pub lost: u64,
    /// Frames that came after a later one (their loss taken back).
    pub late: u64,
    /// The same number twice in a row.
    pub repeats: u64,
    /// Jumps back further than [`MAX_REORDER`]: the sender started its numbers again.
    pub restarts: u64,
}

impl SequenceTracker {
    pub fn observe(&mut self, seq: u8) {
        self.received += 1;
        let Some(last) = self.last else {
            self.last = Some(seq);
            return;
        };
        let behind = last.wrapping_sub(seq);
        if behind == 0 {
            self.repeats += 1;
        } else if behind <= MAX_REORDER {
            self.late += 1;
            self.lost = self.lost.saturating_sub(1);
        } else {
            let skipped = seq.wrapping_sub(last).wrapping_sub(1);
            if skipped < 128 {
                self.lost += u64::from(skipped);
            } else {
                self.restarts += 1;
            }
            self.last = Some(seq);
        }
    }

    /// Lost / (received + lost); `None` before two frames.
    pub fn loss_fraction(&self) -> Option<f64> {
        (self.received >= 2).then(|| self.lost as f64 / (self.received + self.lost) as f64)
    }

    /// The last number followed.
    pub fn last(&self) -> Option<u8> {
        self.last
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn track(seqs: &[u8]) -> SequenceTracker {
        let mut t = SequenceTracker::default();
        for &s in seqs {
            t.observe(s);
        }
        t
    }

    #[test]
    fn consecutive_numbers_lose_nothing_across_the_wrap() {
        let t = track(&[253, 254, 255, 0, 1]);
        assert_eq!((t.received, t.lost, t.late, t.repeats, t.restarts), (5, 0, 0, 0, 0));
        assert_eq!(t.loss_fraction(), Some(0.0));
        assert_eq!(track(&[7]).loss_fraction(), None);
    }

    #[test]
    fn gaps_are_losses_across_the_wrap() {
        let t = track(&[10, 13, 14]);
        assert_eq!(t.lost, 2);
        assert_eq!(t.loss_fraction(), Some(2.0 / 5.0));
        assert_eq!(track(&[254, 1]).lost, 2, "255 and 0");
        // the largest gap read as loss: 127 frames
        assert_eq!(track(&[0, 128]).lost, 127);
    }

    #[test]
    fn a_late_frame_takes_its_loss_back_and_is_not_followed() {
        let t = track(&[5, 7, 6, 8]);
        assert_eq!((t.lost, t.late, t.last()), (0, 1, Some(8)));
        // late without a loss counted (a repeat from long ago): loss never below zero
        let t = track(&[5, 6, 4]);
        assert_eq!((t.lost, t.late, t.last()), (0, 1, Some(6)));
        // the furthest behind a late frame may be
        let t = track(&[100, 100 - MAX_REORDER]);
        assert_eq!((t.late, t.restarts), (1, 0));
    }

    #[test]
    fn a_repeat_counts_once_as_received() {
        let t = track(&[9, 9, 10]);
        assert_eq!((t.received, t.lost, t.repeats, t.late), (3, 0, 1, 0));
    }

    #[test]
    fn a_restarted_sender_is_followed_without_loss() {
        // back by 60: numbers started again
        let t = track(&[60, 61, 1, 2, 3]);
        assert_eq!((t.lost, t.restarts, t.late, t.last()), (0, 1, 0, Some(3)));
        // a jump ahead of 128 or more is a restart too (no 200-frame loss from one number)
        let t = track(&[10, 210, 211]);
        assert_eq!((t.lost, t.restarts), (0, 1));
    }
}
