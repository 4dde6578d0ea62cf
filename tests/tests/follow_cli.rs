//! `bcal calibrate --follow`: live readings in, one JSON estimate per reading out as soon as it is
//! computed. The test is the slow writer: it writes a reading, waits until that reading's estimate has come
//! out, and only then writes the next, so an estimate held back until more input (or the end) fails it.
//! Bad lines are skipped with their line numbers; end of input, --idle-s and SIGINT each end the loop with
//! a summary. The readings are a rest and a 2 A discharge of the base model, one every 10 s.

use bcal_common::battery::{BatteryModel, Degradation, Load};
use bcal_tests::Piped;
use std::io::Write;
use std::time::{Duration, Instant};

const WAIT: Duration = Duration::from_secs(20);

/// (time_s, voltage_v, current_a) every 10 s: 30 s at rest, then 2 A for `loaded` readings.
fn readings(loaded: usize) -> Vec<(f64, f64, f64)> {
    let m = BatteryModel::default();
    let d = Degradation { q_mobile_c: 6000.0, r_o_ohm: 0.14 };
    let mut x = m.initial_state(&d);
    let mut out = Vec::new();
    let mut t = 0.0;
    while out.len() < 3 + loaded {
        let i = if t < 30.0 { 0.0 } else { 2.0 };
        if (t as u64).is_multiple_of(10) {
            out.push((t, m.voltage_v(&x, &d), i));
        }
        x = m.step(&x, Load::CurrentA(i), 1.0, &d).0;
        t += 1.0;
    }
    out
}

fn json(line: &str) -> serde_json::Value {
    serde_json::from_str(line).unwrap_or_else(|e| panic!("not a JSON line: {line} ({e})"))
}

/// Reads until the estimate of `line_no` arrives (or fails the test): every output line names its input
/// line, and none may come for a line not written yet.
fn estimate_of(p: &Piped, line_no: u64) -> serde_json::Value {
    let line = p.next_line(WAIT).unwrap_or_else(|| {
        panic!("no estimate for line {line_no} within {WAIT:?} of writing it; stderr:\n{}", p.stderr())
    });
    let v = json(&line);
    assert_eq!(v["line"], line_no, "estimate out of order: {line}");
    v
}

#[test]
fn follow_stdin_answers_each_reading_before_the_next_and_skips_bad_lines() {
    let mut p = Piped::start("bcal", &["calibrate", "--follow", "-"]);
    p.write_line("time_s,voltage_v,current_a,temperature_c");
    let mut line_no = 1u64;
    let mut skipped = Vec::new();
    let mut last_time = f64::NEG_INFINITY;
    for (k, (t, v, i)) in readings(25).into_iter().enumerate() {
        if k == 4 {
            // A field that is not a number, and a reading back in time: each reported and skipped.
            line_no += 1;
            p.write_line(&format!("{t},abc,{i},24"));
            skipped.push(line_no);
            line_no += 1;
            p.write_line(&format!("{},{v},{i},24", t - 100.0));
            skipped.push(line_no);
        }
        line_no += 1;
        let written = Instant::now();
        p.write_line(&format!("{t},{v:.5},{i},24"));
        let e = estimate_of(&p, line_no);
        assert!(written.elapsed() < WAIT);
        assert_eq!(e["time_s"], t);
        assert!(t > last_time);
        last_time = t;
        let q = e["q_mobile"].as_f64().expect("q_mobile");
        assert!((3500.0..=7500.0).contains(&q), "{e}");
        assert!(e["r_o"].as_f64().is_some_and(|r| r > 0.0), "{e}");
        if i > 0.0 {
            assert_eq!(e["eod_current_a"], 2.0, "{e}");
            assert!(e["eod_s"].as_f64().is_some_and(|eod| eod > t), "the EOD lies ahead: {e}");
        }
        // The slow writer.
        std::thread::sleep(Duration::from_millis(20));
    }
    p.close_stdin();
    let status = p.wait_timeout(WAIT).expect("bcal ends at the end of its input");
    let err = p.stderr();
    assert!(status.success(), "{err}");
    assert!(p.next_line(Duration::from_millis(100)).is_none(), "no output for the bad lines");
    for n in &skipped {
        assert!(err.contains(&format!("line {n}: ")), "line {n} reported:\n{err}");
    }
    assert!(err.contains("field `voltage_v` = `abc` is not a number; skipped"), "{err}");
    assert!(err.contains("does not increase"), "{err}");
    assert!(
        err.contains(&format!(
            "follow: end of input: 28 readings taken, 2 bad lines skipped (lines {}, {})",
            skipped[0], skipped[1]
        )),
        "{err}"
    );
}

/// A header in the middle of the stream (two logs joined; the second names its columns in another order and
/// its current in mA) is read as a header: the rows after it give the estimates the same readings give
/// under one header.
#[test]
fn follow_reads_a_header_in_the_middle_of_the_stream_as_a_header() {
    let rs = readings(20);
    let run = |lines: &[String]| -> (Vec<serde_json::Value>, String) {
        let mut p = Piped::start("bcal", &["calibrate", "--follow", "-"]);
        for l in lines {
            p.write_line(l);
        }
        p.close_stdin();
        let status = p.wait_timeout(WAIT).expect("bcal ends at the end of its input");
        let mut out = Vec::new();
        while let Some(l) = p.next_line(Duration::from_millis(200)) {
            out.push(json(&l));
        }
        let err = p.stderr();
        assert!(status.success(), "{err}");
        (out, err)
    };
    let mut one = vec!["time_s,voltage_v,current_a".to_string()];
    one.extend(rs.iter().map(|(t, v, i)| format!("{t},{v:.5},{i}")));
    let mut two = vec!["time_s,voltage_v,current_a".to_string()];
    two.extend(rs[..10].iter().map(|(t, v, i)| format!("{t},{v:.5},{i}")));
    two.push("current_ma,time_s,voltage_v".to_string());
    two.extend(rs[10..].iter().map(|(t, v, i)| format!("{},{t},{v:.5}", i * 1000.0)));
    let ((a, _), (b, err)) = (run(&one), run(&two));
    assert!(err.contains("line 12: a header again") && err.contains("0 bad lines skipped"), "{err}");
    assert_eq!(a.len(), rs.len());
    assert_eq!(b.len(), rs.len());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!((&x["q_mobile"], &x["r_o"], &x["eod_s"]), (&y["q_mobile"], &y["r_o"], &y["eod_s"]), "{x}\n{y}");
    }
}

#[test]
fn follow_file_reads_what_another_process_appends_and_ends_when_idle() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("live.jsonl");
    let mut f = std::fs::File::create(&path).unwrap();
    let rs = readings(10);
    // The first reading is there before bcal starts; the rest come while it follows.
    writeln!(f, "{{\"time_s\": {}, \"voltage_v\": {}, \"current_a\": {}}}", rs[0].0, rs[0].1, rs[0].2).unwrap();
    f.flush().unwrap();
    let p = Piped::start(
        "bcal",
        &["calibrate", "--follow", path.to_str().unwrap(), "--calibrator", "fit", "--idle-s", "1.5"],
    );
    estimate_of(&p, 1);
    for (k, (t, v, i)) in rs.iter().enumerate().skip(1) {
        // A line written in two parts: nothing is read until its newline.
        let text = format!("{{\"time_s\": {t}, \"voltage_v\": {v}, \"current_a\": {i}, \"temperature_c\": 24.0}}\n");
        let (a, b) = text.split_at(text.len() / 2);
        f.write_all(a.as_bytes()).unwrap();
        f.flush().unwrap();
        std::thread::sleep(Duration::from_millis(60));
        f.write_all(b.as_bytes()).unwrap();
        f.flush().unwrap();
        let e = estimate_of(&p, k as u64 + 1);
        assert_eq!(e["time_s"], *t);
    }
    let mut p = p;
    let status = p.wait_timeout(WAIT).expect("ends after --idle-s without a new line");
    let err = p.stderr();
    assert!(status.success(), "{err}");
    assert!(err.contains("follow: no new line for 1.5 s (--idle-s): 13 readings taken, 0 bad lines skipped"), "{err}");
}

/// A followed file whose writer died mid-line: the cut line is said at the end, not taken; a followed file
/// replaced by another at its path (a log rotated) ends the follow, naming what to do, rather than idling on
/// the old one.
#[test]
fn follow_file_says_what_it_could_not_take_and_refuses_a_replaced_file() {
    let dir = tempfile::tempdir().unwrap();
    let rs = readings(4);
    let rows = |rs: &[(f64, f64, f64)]| -> String {
        let mut text = String::from("time_s,voltage_v,current_a\n");
        text.extend(rs.iter().map(|(t, v, i)| format!("{t},{v:.5},{i}\n")));
        text
    };
    let cut = dir.path().join("cut.csv");
    std::fs::write(&cut, rows(&rs) + "1000,3.9").unwrap();
    let mut p = Piped::start("bcal", &["calibrate", "--follow", cut.to_str().unwrap(), "--idle-s", "1"]);
    let status = p.wait_timeout(WAIT).expect("ends when idle");
    let err = p.stderr();
    assert!(status.success(), "{err}");
    assert!(
        err.contains("the last 8 bytes had no newline") && err.contains(&format!("{} readings taken", rs.len())),
        "{err}"
    );

    let live = dir.path().join("live.csv");
    std::fs::write(&live, rows(&rs[..3])).unwrap();
    let mut p = Piped::start("bcal", &["calibrate", "--follow", live.to_str().unwrap(), "--idle-s", "10"]);
    for k in 1..=3 {
        estimate_of(&p, k + 1);
    }
    std::fs::rename(&live, dir.path().join("live.csv.1")).unwrap();
    std::fs::write(&live, rows(&rs) + &rows(&rs)).unwrap();
    let status = p.wait_timeout(WAIT).expect("ends on the replaced file");
    let err = p.stderr();
    assert!(!status.success() && err.contains("was replaced by another file while followed"), "{err}");
}

#[test]
fn follow_ends_on_ctrl_c_with_a_summary() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("live.csv");
    let rs = readings(3);
    let mut text = String::from("time_s,voltage_v,current_a\n");
    for (t, v, i) in &rs {
        text.push_str(&format!("{t},{v},{i}\n"));
    }
    std::fs::write(&path, text).unwrap();
    let mut p =
        Piped::start("bcal", &["calibrate", "--follow", path.to_str().unwrap(), "--calibrator", "uncalibrated"]);
    for k in 0..rs.len() {
        estimate_of(&p, k as u64 + 2);
    }
    bcal_tests::signal(p.pid(), libc::SIGINT);
    let status = p.wait_timeout(WAIT).expect("Ctrl-C ends the follow");
    let err = p.stderr();
    assert!(status.success(), "{err}");
    assert!(err.contains("follow: stopped (Ctrl-C / SIGTERM): 6 readings taken"), "{err}");
}

#[test]
fn follow_refuses_a_header_without_the_columns_and_a_missing_file() {
    let mut p = Piped::start("bcal", &["calibrate", "--follow", "-"]);
    p.write_line("t,v,i");
    p.close_stdin();
    let status = p.wait_timeout(WAIT).expect("ends");
    assert!(!status.success());
    let err = p.stderr();
    assert!(err.contains("line 1: the header `t,v,i`: no time, no voltage, no current among `t,v,i`"), "{err}");
    let mut p = Piped::start("bcal", &["calibrate", "--follow", "/nonexistent/live.csv"]);
    let status = p.wait_timeout(WAIT).expect("ends");
    assert!(!status.success());
    assert!(p.stderr().contains("--follow /nonexistent/live.csv: no such file"), "{}", p.stderr());
    let dir = tempfile::tempdir().unwrap();
    let mut p = Piped::start("bcal", &["calibrate", "--follow", dir.path().to_str().unwrap()]);
    let status = p.wait_timeout(WAIT).expect("ends");
    assert!(!status.success());
    assert!(p.stderr().contains("a folder, not a log") && p.stderr().contains("--data"), "{}", p.stderr());
}

/// A stream on a diagnosis without the cell's config predicts at the cut-off the diagnosis had from the cell's
/// protocol, and says so; a cut-off given wins; the prior stays the setting's.
#[test]
fn follow_on_a_diagnosis_predicts_at_its_cut_off() {
    let dir = tempfile::tempdir().unwrap();
    let diag = dir.path().join("diagnosis.json");
    let cycles: Vec<_> =
        (1..=6).map(|c| serde_json::json!({"cycle": c, "q_mobile_c": 6400.0 + f64::from(c), "r_o_ohm": 0.1})).collect();
    let file = serde_json::json!({"cell": "B0005", "settings": {"cutoff_v": 2.7, "cutoff_given": true},
        "extended": {"causes": [], "params": {}, "train_cycles": cycles}});
    std::fs::write(&diag, file.to_string()).unwrap();
    for (extra, cut) in [(None, "2.7"), (Some("2.9"), "2.9")] {
        let mut args = vec!["calibrate", "--follow", "-", "--model", diag.to_str().unwrap()];
        if let Some(v) = extra {
            args.extend(["--cutoff-v", v]);
        }
        let mut p = Piped::start("bcal", &args);
        p.write_line("time_s,voltage_v,current_a");
        p.close_stdin();
        assert!(p.wait_timeout(WAIT).expect("ends").success(), "{}", p.stderr());
        let err = p.stderr();
        assert!(err.contains(&format!("cut-off {cut} V, prior q_mobile 5500 C, r_o 0.15 ohm")), "{err}");
        assert_eq!(err.contains("--model: cut-off 2.7 V, the diagnosis's"), extra.is_none(), "{err}");
    }
}

#[test]
fn follow_runs_an_rl_policy_file() {
    let dir = tempfile::tempdir().unwrap();
    let policy = dir.path().join("p.bcalpol");
    bcal_tests::write_test_policy(&policy);
    let arg = format!("rl:{}", policy.display());
    let mut p = Piped::start("bcal", &["calibrate", "--follow", "-", "--calibrator", &arg]);
    p.write_line("time_s,voltage_v,current_a");
    let mut q = Vec::new();
    for (k, (t, v, i)) in readings(20).into_iter().enumerate() {
        p.write_line(&format!("{t},{v},{i}"));
        q.push(estimate_of(&p, k as u64 + 2)["q_mobile"].as_f64().unwrap());
    }
    p.close_stdin();
    let status = p.wait_timeout(WAIT).expect("ends");
    assert!(status.success(), "{}", p.stderr());
    assert!(p.stderr().contains("follow: rl on standard input"), "{}", p.stderr());
    // The policy's actions move the estimate off the prior.
    assert!(q.iter().any(|x| (x - 5500.0).abs() > 1.0), "{q:?}");
}

/// A model with the doctor's `thermal` runs on the measured temperature: a CSV stream without the column is
/// refused at its header, naming what to give, as `bcal calibrate --data` refuses such records; JSON lines
/// without one run at the ambient, said once.
#[test]
fn follow_on_a_thermal_model_needs_temperatures() {
    let dir = tempfile::tempdir().unwrap();
    let diag = dir.path().join("diagnosis.json");
    let file = serde_json::json!({"cell": "B0055", "extended": {"causes": ["thermal"],
        "params": {"ro_activation_k": 2000.0}}});
    std::fs::write(&diag, file.to_string()).unwrap();
    let args = ["calibrate", "--follow", "-", "--model", diag.to_str().unwrap()];
    let mut p = Piped::start("bcal", &args);
    p.write_line("time_s,voltage_v,current_a");
    p.close_stdin();
    assert!(!p.wait_timeout(WAIT).expect("ends").success());
    let err = p.stderr();
    assert!(err.contains("line 1: the header has no temperature column") && err.contains("temperature_c"), "{err}");
    let mut p = Piped::start("bcal", &args);
    for k in 0..3 {
        p.write_line(&format!("{{\"time_s\": {}, \"voltage_v\": 4.1, \"current_a\": 2.0}}", 10 * k));
    }
    p.close_stdin();
    assert!(p.wait_timeout(WAIT).expect("ends").success(), "{}", p.stderr());
    let err = p.stderr();
    assert_eq!(err.matches("runs at the ambient").count(), 1, "{err}");
    assert!(err.contains("line 1: no temperature, nor any before"), "{err}");
    // With temperatures, nothing is said.
    let mut p = Piped::start("bcal", &args);
    p.write_line("time_s,voltage_v,current_a,temperature_c");
    p.write_line("0,4.1,2.0,5.0");
    p.close_stdin();
    assert!(p.wait_timeout(WAIT).expect("ends").success(), "{}", p.stderr());
    assert!(!p.stderr().contains("runs at the ambient"), "{}", p.stderr());
}
