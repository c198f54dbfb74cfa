//! "Latest sample wins, buttons survive": the one rule for folding phone samples that queued up while the
//! previous one was still in flight. The gateway's slot, the SDK's teleop session and the server's teleop
//! round all fold with [`PendingSample`], so a burst from the network plans only the newest pose but never
//! loses a button edge (a lost "stop recording" or clutch release is worse than a late one).

use crate::v1::{PhoneSample, TrackingState};

/// At most one sample waiting to be sent or planned: the fold of every sample pushed since the last take.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct PendingSample {
    sample: Option<PhoneSample>,
}

impl PendingSample {
    /// Folds `newer` in. The result is `newer` (its seq, capture time and pose) with every button event of the
    /// pending sample before its own; when `newer` carries no pose, the pending pose is kept, so a button-only
    /// sample never erases the newest pose. A pending "tracking lost/limited" is kept unless a newer pose
    /// says otherwise. Returns true when a pending pose was superseded by a newer one (it will never be
    /// planned).
    pub fn push(&mut self, mut newer: PhoneSample) -> bool {
        let Some(old) = self.sample.take() else {
            self.sample = Some(newer);
            return false;
        };
        let pose_superseded = old.tracking_from_phone.is_some() && newer.tracking_from_phone.is_some();
        if !old.buttons.is_empty() {
            let mut buttons = old.buttons;
            buttons.append(&mut newer.buttons);
            newer.buttons = buttons;
        }
        if newer.tracking_from_phone.is_none() {
            if old.tracking_from_phone.is_some() {
                newer.tracking_from_phone = old.tracking_from_phone;
            }
            // Without a pose of its own, a newer sample only says something about tracking if it is bad news.
            if !tracking_lost(newer.tracking) {
                newer.tracking = old.tracking;
            }
        }
        if newer.arm.is_empty() {
            newer.arm = old.arm;
        }
        if newer.client_name.is_empty() {
            newer.client_name = old.client_name;
        }
        newer.take_over |= old.take_over;
        self.sample = Some(newer);
        pose_superseded
    }

    /// The folded sample, leaving nothing pending.
    pub fn take(&mut self) -> Option<PhoneSample> {
        self.sample.take()
    }

    /// True when nothing is pending.
    pub fn is_empty(&self) -> bool {
        self.sample.is_none()
    }
}

/// True when `tracking` (a wire `TrackingState`) says the phone's pose cannot be trusted.
pub fn tracking_lost(tracking: i32) -> bool {
    matches!(
        TrackingState::try_from(tracking),
        Ok(TrackingState::Lost | TrackingState::Limited)
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::buttons;
    use crate::v1::{ButtonEvent, Pose};
    use proptest::prelude::*;

    fn sample(seq: u64, x: Option<f64>, tracking: TrackingState, buttons: Vec<ButtonEvent>) -> PhoneSample {
        PhoneSample {
            seq,
            capture_time_ns: i64::try_from(seq).unwrap() * 1000,
            tracking_from_phone: x.map(|x| Pose::from_parts([x, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])),
            tracking: tracking as i32,
            buttons,
            ..PhoneSample::default()
        }
    }

    #[test]
    fn a_button_only_sample_keeps_the_pending_pose_and_appends_its_buttons() {
        let mut pending = PendingSample::default();
        assert!(!pending.push(sample(
            1,
            Some(0.1),
            TrackingState::Tracking,
            vec![buttons::clutch_engage()]
        )));
        assert!(pending.push(sample(2, Some(0.2), TrackingState::Tracking, vec![])));
        assert!(!pending.push(sample(
            3,
            None,
            TrackingState::Unspecified,
            vec![buttons::clutch_disengage()]
        )));
        let got = pending.take().unwrap();
        assert!(pending.is_empty());
        assert_eq!(got.seq, 3);
        assert_eq!(
            got.tracking_from_phone,
            Some(Pose::from_parts([0.2, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]))
        );
        assert_eq!(got.tracking, TrackingState::Tracking as i32);
        assert_eq!(
            got.buttons,
            [buttons::clutch_engage(), buttons::clutch_disengage()]
        );
    }

    #[test]
    fn lost_tracking_survives_a_later_sample_without_pose_but_not_a_newer_pose() {
        let mut pending = PendingSample::default();
        pending.push(sample(1, Some(0.1), TrackingState::Tracking, vec![]));
        pending.push(sample(2, None, TrackingState::Lost, vec![]));
        pending.push(sample(3, None, TrackingState::Unspecified, vec![]));
        assert!(tracking_lost(pending.take().unwrap().tracking));
        pending.push(sample(4, None, TrackingState::Lost, vec![]));
        pending.push(sample(5, Some(0.5), TrackingState::Tracking, vec![]));
        assert!(!tracking_lost(pending.take().unwrap().tracking));
    }

    #[test]
    fn the_first_sample_names_arm_client_and_take_over_for_the_fold() {
        let mut pending = PendingSample::default();
        pending.push(PhoneSample {
            arm: "left".into(),
            client_name: "phone".into(),
            take_over: true,
            ..PhoneSample::default()
        });
        pending.push(sample(2, Some(0.2), TrackingState::Tracking, vec![]));
        let got = pending.take().unwrap();
        assert_eq!(
            (got.arm.as_str(), got.client_name.as_str(), got.take_over),
            ("left", "phone", true)
        );
    }

    fn any_button() -> impl Strategy<Value = ButtonEvent> {
        prop_oneof![
            Just(buttons::clutch_engage()),
            Just(buttons::clutch_disengage()),
            Just(buttons::clutch_toggle()),
            Just(buttons::gripper_toggle()),
            (0.0..=1.0f64).prop_map(buttons::gripper_set),
            Just(buttons::record_stop()),
        ]
    }

    fn any_burst() -> impl Strategy<Value = Vec<PhoneSample>> {
        prop::collection::vec(
            (
                prop::option::of(-1.0..1.0f64),
                prop::collection::vec(any_button(), 0..4),
            ),
            1..40,
        )
        .prop_map(|items| {
            items
                .into_iter()
                .enumerate()
                .map(|(i, (x, b))| sample(i as u64 + 1, x, TrackingState::Tracking, b))
                .collect()
        })
    }

    proptest! {
        /// Taken at any points of a burst, the folds together carry every button edge exactly once and in order,
        /// each fold carries the newest pose pushed before it, and the newest seq.
        #[test]
        fn no_button_is_lost_and_the_pose_is_always_the_newest(
            burst in any_burst(),
            takes in prop::collection::vec(any::<bool>(), 40),
        ) {
            let mut pending = PendingSample::default();
            let mut taken = Vec::new();
            let mut newest_pose = None;
            let mut newest_seq = 0;
            let mut superseded = 0;
            let mut poses_in_fold = 0u64;
            let check = |fold: PhoneSample, newest_pose: &Option<Pose>, newest_seq: u64, taken: &mut Vec<ButtonEvent>| {
                prop_assert_eq!(&fold.tracking_from_phone, newest_pose);
                prop_assert_eq!(fold.seq, newest_seq);
                taken.extend(fold.buttons);
                Ok(())
            };
            for (s, take) in burst.iter().zip(takes.iter().chain(std::iter::repeat(&false))) {
                if s.tracking_from_phone.is_some() {
                    newest_pose.clone_from(&s.tracking_from_phone);
                    poses_in_fold += 1;
                }
                newest_seq = s.seq;
                superseded += u64::from(pending.push(s.clone()));
                if *take {
                    check(pending.take().unwrap(), &newest_pose, newest_seq, &mut taken)?;
                    prop_assert_eq!(superseded, poses_in_fold.saturating_sub(1));
                    superseded = 0;
                    poses_in_fold = 0;
                    newest_pose = None;
                }
            }
            if let Some(fold) = pending.take() {
                check(fold, &newest_pose, newest_seq, &mut taken)?;
            }
            let sent: Vec<ButtonEvent> = burst.into_iter().flat_map(|s| s.buttons).collect();
            prop_assert_eq!(taken, sent);
        }
    }
}
