//! `relightd recording check FILE` and `relightd recording repair IN OUT`: what a recording still
//! holds, and a complete copy of it (summary and footer written) for tools that need them.

use std::io::BufWriter;
use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use relight_core::recording::salvage::{self, Inspection};
use relight_core::recording::{RecordingOptions, RecordingReader, RecordingWriter};
use relight_daemon::sinks::safe_file::{Existing, create_regular};

#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// Read every message and report what is there and what is lost; exits 1 when the file is
    /// damaged (cut, corrupt chunks, no summary).
    Check {
        /// The MCAP recording to read.
        file: PathBuf,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Copy every readable message of IN into OUT, a complete recording (summary, chunk index
    /// and footer) with IN's metadata and calibration, in the current format (so it also
    /// converts a format-1 recording).
    Repair {
        /// The recording to read (damaged, or in an older format).
        input: PathBuf,
        /// Where the complete copy goes.
        output: PathBuf,
        /// Replace OUT if it exists (it is refused otherwise).
        #[arg(long)]
        overwrite: bool,
    },
}

pub fn run(command: Command) -> Result<std::process::ExitCode> {
    match command {
        Command::Check { file, json } => {
            let reader = open(&file)?;
            let found = salvage::inspect(&reader);
            if json {
                println!("{}", serde_json::to_string_pretty(&found)?);
            } else {
                print!("{}", report(&file, &found));
            }
            Ok(if found.is_clean() {
                std::process::ExitCode::SUCCESS
            } else {
                std::process::ExitCode::FAILURE
            })
        }
        Command::Repair {
            input,
            output,
            overwrite,
        } => {
            if same_file(&input, &output) {
                bail!("{}: IN and OUT are the same file", output.display());
            }
            let reader = open(&input)?;
            let file = create_regular(&output, Existing::from_overwrite(overwrite))?;
            let mut writer = RecordingWriter::with_options(
                BufWriter::with_capacity(1 << 20, file),
                reader.meta(),
                &RecordingOptions::default(),
            )?;
            let found = salvage::salvage(&reader, &mut writer)?;
            let summary = writer
                .finish()
                .with_context(|| format!("finishing {}", output.display()))?;
            print!("{}", report(&input, &found));
            println!(
                "wrote {}: {} messages in {} chunks, with summary and footer",
                output.display(),
                found.total_messages(),
                summary.chunks
            );
            Ok(std::process::ExitCode::SUCCESS)
        }
    }
}

fn open(path: &std::path::Path) -> Result<RecordingReader> {
    RecordingReader::open(path).with_context(|| path.display().to_string())
}

fn same_file(a: &std::path::Path, b: &std::path::Path) -> bool {
    match (std::fs::canonicalize(a), std::fs::canonicalize(b)) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    }
}

fn report(path: &std::path::Path, found: &Inspection) -> String {
    let mut out = format!(
        "{}: {}\n",
        path.display(),
        if found.is_clean() {
            "complete"
        } else {
            "damaged"
        }
    );
    out += &format!(
        "  format   {}\n",
        found
            .format_version
            .map_or("another tool's bag".to_owned(), |v| format!("relight {v}"))
    );
    for (stream, n) in &found.messages {
        out += &format!("  {stream:<8} {n} messages\n");
    }
    if found.truth_messages > 0 {
        out += &format!("  truth    {} messages\n", found.truth_messages);
    }
    if found.output_messages > 0 {
        out += &format!("  outputs  {} messages\n", found.output_messages);
    }
    out += &format!(
        "  summary  {}\n  lost     {} corrupt chunks, {} undecodable messages\n",
        if found.has_summary {
            "present"
        } else {
            "missing"
        },
        found.corrupt_chunks,
        found.undecodable
    );
    for warning in &found.warnings {
        out += &format!("  warning  {warning}\n");
    }
    out
}
