// Compile contracts/AuthROS.sol with the pinned solc (npm) into contracts/build/AuthROS.json.
//
//   node contracts/build.mjs          write the artifact
//   node contracts/build.mjs --check  exit 1 if the committed artifact is stale
//
// The output is deterministic: same source and compiler, same bytes (sorted keys, no
// metadata hash in the bytecode, source unit named by its repository path).
import { createHash } from "node:crypto";
import { mkdirSync, readFileSync, writeFileSync } from "node:fs";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

import solc from "solc";

const SOLC_VERSION = "0.8.30";
const CONTRACT = "AuthROS";
const SOURCE_PATH = "contracts/AuthROS.sol";
const ARTIFACT_PATH = "contracts/build/AuthROS.json";
const SETTINGS = {
  evmVersion: "paris",
  optimizer: { enabled: true, runs: 200 },
  // No IPFS/Swarm hash of the metadata: bytecode must not depend on paths or comments layout.
  metadata: { bytecodeHash: "none" },
  outputSelection: {
    [SOURCE_PATH]: {
      [CONTRACT]: ["abi", "evm.bytecode.object", "evm.deployedBytecode.object", "metadata"],
    },
  },
};

const repoRoot = join(dirname(fileURLToPath(import.meta.url)), "..");

function fail(message) {
  console.error(`build.mjs: ${message}`);
  process.exit(1);
}

function sortKeys(value) {
  if (Array.isArray(value)) return value.map(sortKeys);
  if (value !== null && typeof value === "object") {
    return Object.fromEntries(
      Object.keys(value)
        .sort()
        .map((key) => [key, sortKeys(value[key])]),
    );
  }
  return value;
}

function compile() {
  const version = solc.version();
  if (!version.startsWith(`${SOLC_VERSION}+`)) {
    fail(`solc ${version} found, ${SOLC_VERSION} pinned: run npm ci`);
  }
  const sourceBytes = readFileSync(join(repoRoot, SOURCE_PATH));
  const input = {
    language: "Solidity",
    sources: { [SOURCE_PATH]: { content: sourceBytes.toString("utf8") } },
    settings: SETTINGS,
  };
  const output = JSON.parse(solc.compile(JSON.stringify(input)));
  const diagnostics = output.errors ?? [];
  for (const d of diagnostics) console.error(d.formattedMessage ?? d.message);
  if (diagnostics.some((d) => d.severity === "error")) fail("compilation failed");

  const contract = output.contracts?.[SOURCE_PATH]?.[CONTRACT];
  if (!contract) fail(`no contract ${CONTRACT} in ${SOURCE_PATH}`);
  // The compiler hashes the source itself; taking its keccak256 avoids a second implementation.
  const metadata = JSON.parse(contract.metadata);
  const artifact = {
    contractName: CONTRACT,
    abi: contract.abi,
    bytecode: `0x${contract.evm.bytecode.object}`,
    deployedBytecode: `0x${contract.evm.deployedBytecode.object}`,
    compiler: {
      version,
      evmVersion: SETTINGS.evmVersion,
      optimizer: SETTINGS.optimizer,
    },
    source: {
      path: SOURCE_PATH,
      keccak256: metadata.sources[SOURCE_PATH].keccak256,
      sha256: `0x${createHash("sha256").update(sourceBytes).digest("hex")}`,
    },
  };
  return `${JSON.stringify(sortKeys(artifact), null, 2)}\n`;
}

const text = compile();
const artifactFile = join(repoRoot, ARTIFACT_PATH);
if (process.argv.includes("--check")) {
  let committed = null;
  try {
    committed = readFileSync(artifactFile, "utf8");
  } catch {
    fail(`${ARTIFACT_PATH} is missing: run node contracts/build.mjs`);
  }
  if (committed !== text) {
    fail(`${ARTIFACT_PATH} is stale (differs from a fresh compile): run node contracts/build.mjs`);
  }
  console.log(`${ARTIFACT_PATH} is up to date`);
} else {
  mkdirSync(dirname(artifactFile), { recursive: true });
  writeFileSync(artifactFile, text);
  console.log(`wrote ${ARTIFACT_PATH}`);
}
