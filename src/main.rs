fn main() {
    std::process::exit(fwlidar::cli::main());
}
