//! LAC learner (tch). Contents arrive with the training issue.
